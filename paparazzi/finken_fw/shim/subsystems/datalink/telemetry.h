/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SUBSYSTEMS_TELEMETRY_H
#define FINKEN_V5_SUBSYSTEMS_TELEMETRY_H
#include "finken_v5_compat.h"
/* v5's generated headers gave every firmware file the headers of all loaded modules:
 * finken_wall_avoid.c, finken_rc_passthrough.c and finken_model_sensors.c use
 * finken_system_set_point, finken_sensor_model and finken_actuators_set_point without
 * including their headers. Here they come with this header (the firmware's own headers, found
 * on the version's include path). */
#include "modules/sonar/sonar_array_i2c.h"
#include "modules/finken_model/finken_model_sensors.h"
#include "modules/finken_model/finken_model_system.h"
#include "modules/finken_model/finken_model_actuators.h"
#include "modules/finken_ir_adc/finken_ir_adc.h"
#endif
