/*
 * Twinswarm FINken module for Paparazzi: the FINken's sonars, IR height, virtual-sonar
 * uplink (SONAR_UPLINK) and Wall-Avoid.
 *
 * This file is part of Twinswarm's Paparazzi bindings; like the Paparazzi code it is
 * built into, it is GPL (v2 or later).
 *
 * Sonar order everywhere here: front, right, back, left (body frame, 90 deg apart), as in
 * nps_fdm_twinswarm.h. Distances in m, NaN = nothing (no echo / no virtual reading).
 *
 * Wall-Avoid outputs are in DEGREES, in Paparazzi's attitude convention, for a flight plan's
 * <attitude roll="twinswarm_wall_avoid_roll" pitch="twinswarm_wall_avoid_pitch" .../> stage
 * (the flight plan generator wraps both in RadOfDeg):
 *   roll  > 0: right side down, the copter accelerates to its right;
 *   pitch > 0: nose up, the copter accelerates backward (a wall ahead gives pitch > 0).
 */

#ifndef TWINSWARM_FINKEN_H
#define TWINSWARM_FINKEN_H

#include "std.h"

#define TWINSWARM_FRONT 0
#define TWINSWARM_RIGHT 1
#define TWINSWARM_BACK  2
#define TWINSWARM_LEFT  3

/** last readings of the (simulated) real sonars, m, NaN = no echo */
extern float twinswarm_sonar_real_m[4];
/** last virtual readings from SONAR_UPLINK, m, NaN = none (also once stale) */
extern float twinswarm_sonar_virtual_m[4];
/** min(real, virtual) per direction, m, NaN = nothing */
extern float twinswarm_sonar_fused_m[4];
/** the sonar filter's moving averages of the fused readings (clamped), m */
extern float twinswarm_sonar_filtered_m[4];
/** IR height, m, NaN = out of range */
extern float twinswarm_ir_height_m;

/** Wall-Avoid output (lead-lag + cruise), deg, see above */
extern float twinswarm_wall_avoid_roll;
extern float twinswarm_wall_avoid_pitch;
/** the lead-lag's part alone, deg */
extern float twinswarm_wall_avoid_ll_roll;
extern float twinswarm_wall_avoid_ll_pitch;

/* settings (DL_SETTING) */
/** cruise tilt forward, deg (> 0 flies forward) */
extern float twinswarm_wa_cruise_fwd;
/** cruise tilt to the right, deg (> 0 flies right) */
extern float twinswarm_wa_cruise_right;
/** 1: a cruise component reverses when its filtered sonar is closer than the bounce distance */
extern uint8_t twinswarm_wa_bounce;
/** Wall-Avoid's goal (safety) distance, m (the firmware's SONAR_DIFF_GOAL_DIST) */
extern float twinswarm_wa_goal_dist;
/** a virtual reading is ignored this long after its SONAR_UPLINK, s (autopilot time) */
extern float twinswarm_virtual_timeout;

extern void twinswarm_finken_init(void);
/** sonar/IR sampling, fusion, filter and Wall-Avoid; runs at TWINSWARM_FINKEN_SONAR_FREQ (20 Hz) */
extern void twinswarm_finken_periodic(void);
extern void twinswarm_finken_parse_SONAR_UPLINK(uint8_t *buf);

#endif /* TWINSWARM_FINKEN_H */
