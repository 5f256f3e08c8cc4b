/*
 * This file is part of Twinswarm's Paparazzi bindings (GPL v2 or later).
 *
 * The FINken firmware's module entry points, for Paparazzi's generated modules.h. The
 * firmware's own headers include v5 header names (the shim folder), which must not reach
 * v6.4's own files: generated/modules.h is included by most of them.
 */
#ifndef FINKEN_FW_API_H
#define FINKEN_FW_API_H

#include <stdint.h>

extern void sonar_array_i2c_init(void);
extern void sonar_array_i2c_periodic(void);
extern void finken_sensor_model_init(void);
extern void finken_sensor_model_periodic(void);
extern void finken_system_model_init(void);
extern void finken_system_model_periodic(void);
extern void finken_actuators_model_init(void);
extern void finken_actuators_model_periodic(void);
extern void finken_ir_adc_init(void);
extern void finken_ir_adc_periodic(void);
extern void finken_wall_avoid_init(void);
extern void finken_wall_avoid_periodic(void);
extern void finken_rc_passthrough_periodic(void);
/* 2015-07 */
extern void finken_environment_model_init(void);
extern void finken_environment_model_periodic(void);
extern void finken_fw_nps_sonar_uplink(uint8_t *buf);

#endif
