/*
 * Twinswarm flight model for Paparazzi NPS: what the world sends beyond NpsFdm.
 *
 * This file is part of Twinswarm's Paparazzi bindings; like the Paparazzi code it is
 * built into, it is GPL (v2 or later).
 *
 * The last values received from the Twinswarm world (updated every NPS step, from the
 * NPS main-loop thread, before the sensors and the autopilot run). A Paparazzi module
 * built for the nps target can read them to feed the FINken's sonar array and IR height
 * sensor, e.g. as ABI AGL / OBSTACLE messages.
 */

#ifndef NPS_FDM_TWINSWARM_H
#define NPS_FDM_TWINSWARM_H

#ifdef __cplusplus
extern "C" {
#endif

#include <stdint.h>

/** the four sonars, front, right, back, left (body frame, 90° apart), in m; NaN = no echo */
extern float twinswarm_sonar_m[4];
/** the downward IR height sensor, in m; NaN = nothing in range */
extern float twinswarm_ir_m;
/** 1 once the world reported the copter crashed */
extern uint8_t twinswarm_crashed;
/** world time of the last state received, s */
extern double twinswarm_time_s;
/** number of the last step exchanged with the world */
extern uint64_t twinswarm_step;

#define TWINSWARM_SONAR_FRONT 0
#define TWINSWARM_SONAR_RIGHT 1
#define TWINSWARM_SONAR_BACK  2
#define TWINSWARM_SONAR_LEFT  3

#ifdef __cplusplus
}
#endif

#endif /* NPS_FDM_TWINSWARM_H */
