/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SENSOR_FILTER_H
#define FINKEN_V5_SENSOR_FILTER_H
/* fink3.xml loads sensor_filter.xml, a FINken-fork module that is not among the copies: this
   stand-in provides what finken_model_sensors.c reads of it (sensor_filtered.acceleration,
   which the firmware overwrites with imu.accel on the next line); finken_fw_nps.c fills it
   with the IMU's acceleration (no filter). */
#include "math/pprz_algebra_int.h"
struct finken_v5_sensor_filter_s { struct Int32Vect3 acceleration; struct Int32Rates rates; };
extern struct finken_v5_sensor_filter_s sensor_filtered;
#endif
