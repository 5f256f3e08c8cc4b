/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SUBSYSTEMS_IMU_H
#define FINKEN_V5_SUBSYSTEMS_IMU_H
#include "modules/imu/imu.h"
/* v5: struct Imu had .gyro and .accel (scaled, Int32); v6.4 has per-sensor arrays. The firmware
   (finken_model_sensors.c) reads imu.gyro / imu.accel: it gets the glue's mirror of v6.4's first
   gyro/accel (finken_fw_nps.c, refreshed every autopilot period). */
struct finken_v5_imu_s { struct Int32Rates gyro; struct Int32Vect3 accel; struct Int32Vect3 mag; };
extern struct finken_v5_imu_s finken_v5_imu;
#define imu finken_v5_imu
#endif
