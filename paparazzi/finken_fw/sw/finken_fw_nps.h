/*
 * This file is part of Twinswarm's Paparazzi bindings (GPL v2 or later).
 *
 * The FINken firmware's hardware edge in NPS (nps target only): what the Twinswarm world
 * measured for this copter (nps_fdm_twinswarm.h) reaches the firmware's own drivers through
 * the peripherals they use, so that their own code decodes it.
 *  - sonar_array_i2c: the I2C bus i2c1 (SONAR_I2C_DEV). A ranging command (write 81 = "range
 *    in cm" to SRF 0x71..0x74) latches the world's reading of that sonar (front, right, back,
 *    left); the 2-byte read that follows returns it big-endian in cm, as the SRF02 does; no echo
 *    (NaN) reads 0.
 *  - finken_ir_adc: its ADC buffer. adc_buf_channel (linked with --wrap) records the
 *    firmware's buffer; every autopilot period it is filled with the ADC count that the
 *    firmware's own table (finken_ir_adc.c, inverted here) turns back into the world's IR
 *    distance; NaN reads as nothing in range (count 0, the table's far end).
 *  - the v5 imu.gyro/imu.accel mirror and sensor_filtered (see the shim headers);
 *  - arming: the real FINken was armed by the pilot's RC kill switch; NPS runs without RC, so
 *    the motors are switched on once the AHRS has an attitude (AP_MODE_NAV).
 *  - electrical.vsupply: v5 counted decivolts (uint16), v6.4 volts (float). NPS's battery is
 *    reported to the firmware's flight plan in the unit it compares with (60 > vsupply).
 */
#ifndef FINKEN_FW_NPS_H
#define FINKEN_FW_NPS_H

#include "std.h"

extern void finken_fw_nps_init(void);
extern void finken_fw_nps_periodic(void);

/** the last ADC count written for the IR and the distance it stands for (debugging) */
extern uint16_t finken_fw_nps_ir_count;
extern float finken_fw_nps_ir_m;
/** firmware's ADC table inverted: the count that its interpolation maps to d (m) */
extern uint16_t finken_fw_ir_count_of_distance(float d);

#endif
