/*
 * Twinswarm FINken module for Paparazzi: the FINken's sonars, IR height, virtual-sonar
 * uplink (SONAR_UPLINK) and Wall-Avoid.
 *
 * This file is part of Twinswarm's Paparazzi bindings; like the Paparazzi code it is
 * built into, it is GPL (v2 or later).
 *
 * What it does, every 1/TWINSWARM_FINKEN_SONAR_FREQ s of autopilot time (sys_time, which NPS
 * counts in steps; never the wall clock):
 *  - reads the four sonars and the IR height the Twinswarm world sent (nps target: the globals
 *    of nps_fdm_twinswarm.h); publishes the IR height as ABI AGL (sender
 *    TWINSWARM_FINKEN_IR_AGL_ID) when it is in range;
 *  - fuses each direction with the last SONAR_UPLINK for this aircraft:
 *    fused = min(real, virtual), a virtual reading counting for twinswarm_virtual_timeout
 *    (0.5 s) after its message; 0 cm and >= 765 cm mean "no virtual reading";
 *  - Wall-Avoid as the FINken firmware flew it (finken_sonar_filter + finken_wall_avoid;
 *    ported from Twinswarm's crates/sim-core/src/control.rs, wall_avoid_firmware): each fused
 *    reading (one sonar per update, round robin, as sonar_array_i2c read them; NaN = no echo
 *    counts as the far clamp) is clamped to [FILTER_MIN, FILTER_MAX] and averaged over the
 *    last FILTER_LEN readings of that sonar; per axis the difference of opposite sonars, each
 *    capped at the goal distance G (x = min(back,G) - min(front,G), y = min(right,G) -
 *    min(left,G), m), goes through the lead-lag Kp (1 + Tv s) / (1 + T1 s), Tustin at
 *    UPDATE_FREQ (5 Hz), output capped at +-MAX_CONTROL deg: pitch = u_x, roll = u_y (deg).
 *  - plus a "cruise" tilt (the pilot input of the firmware), each component scaled down
 *    linearly to 0 between G and GUARD_DIST on the side it flies towards (the lead-lag's lead,
 *    Tv = 2.29 s, overshoots: the copter swings back to the opposite wall by itself); with
 *    twinswarm_wa_bounce (on by default; not in the firmware), a cruise component also
 *    reverses when the filtered distance it flies towards drops below BOUNCE_DIST (default G)
 *    and the opposite side is farther.
 */

#include "modules/twinswarm/twinswarm_finken.h"

#include <math.h>

#include "generated/airframe.h"
#include "mcu_periph/sys_time.h"
#include "modules/core/abi.h"
#include "modules/datalink/datalink.h"
#include "pprzlink/dl_protocol.h"

#if PERIODIC_TELEMETRY
#include "modules/datalink/telemetry.h"
#endif

/* the nps target (USE_NPS): the readings come from the Twinswarm FDM */
#ifdef USE_NPS
#include "nps_fdm_twinswarm.h"
#endif

/* ---- parameters (airframe section TWINSWARM_FINKEN, prefix TWINSWARM_FINKEN_) ---- */

/** must match the periodic's freq in twinswarm_finken.xml */
#ifndef TWINSWARM_FINKEN_SONAR_FREQ
#define TWINSWARM_FINKEN_SONAR_FREQ 20.f
#endif
/** one sonar per update (FINken sonar_array_i2c), else all four every update */
#ifndef TWINSWARM_FINKEN_SONAR_ROUND_ROBIN
#define TWINSWARM_FINKEN_SONAR_ROUND_ROBIN TRUE
#endif
#ifndef TWINSWARM_FINKEN_IR_AGL_ID
#define TWINSWARM_FINKEN_IR_AGL_ID 210
#endif
#ifndef TWINSWARM_FINKEN_VIRTUAL_TIMEOUT
#define TWINSWARM_FINKEN_VIRTUAL_TIMEOUT 0.5f
#endif
/** SONAR_UPLINK value meaning "nothing", cm (and anything above) */
#ifndef TWINSWARM_FINKEN_VIRTUAL_NONE_CM
#define TWINSWARM_FINKEN_VIRTUAL_NONE_CM 765
#endif

/* Wall-Avoid (defaults: Twinswarm's WallAvoidSpec, i.e. the FINken fork's
 * conf/modules/finken_wall_avoid/common.xml set "phase margin 40deg, t_max 2.0 s", MAX_CONTROL 8) */
#ifndef TWINSWARM_FINKEN_WA_GOAL_DIST
#define TWINSWARM_FINKEN_WA_GOAL_DIST 1.2f
#endif
#ifndef TWINSWARM_FINKEN_WA_GUARD_DIST
#define TWINSWARM_FINKEN_WA_GUARD_DIST 0.7f
#endif
#ifndef TWINSWARM_FINKEN_WA_FILTER_MIN
#define TWINSWARM_FINKEN_WA_FILTER_MIN 0.2f
#endif
#ifndef TWINSWARM_FINKEN_WA_FILTER_MAX
#define TWINSWARM_FINKEN_WA_FILTER_MAX 3.0f
#endif
#ifndef TWINSWARM_FINKEN_WA_FILTER_LEN
#define TWINSWARM_FINKEN_WA_FILTER_LEN 3
#endif
#ifndef TWINSWARM_FINKEN_WA_UPDATE_FREQ
#define TWINSWARM_FINKEN_WA_UPDATE_FREQ 5.0f
#endif
#ifndef TWINSWARM_FINKEN_WA_CONTROL_GAIN
#define TWINSWARM_FINKEN_WA_CONTROL_GAIN 3.65f
#endif
#ifndef TWINSWARM_FINKEN_WA_CONTROL_HOLD_TIME
#define TWINSWARM_FINKEN_WA_CONTROL_HOLD_TIME 2.29f
#endif
#ifndef TWINSWARM_FINKEN_WA_CONTROL_DELAY_TIME
#define TWINSWARM_FINKEN_WA_CONTROL_DELAY_TIME 0.213f
#endif
#ifndef TWINSWARM_FINKEN_WA_MAX_CONTROL
#define TWINSWARM_FINKEN_WA_MAX_CONTROL 8.0f
#endif
/* cruise (deg) and bounce */
#ifndef TWINSWARM_FINKEN_WA_CRUISE_FWD
#define TWINSWARM_FINKEN_WA_CRUISE_FWD 1.0f
#endif
#ifndef TWINSWARM_FINKEN_WA_CRUISE_RIGHT
#define TWINSWARM_FINKEN_WA_CRUISE_RIGHT 0.6f
#endif
#ifndef TWINSWARM_FINKEN_WA_BOUNCE
#define TWINSWARM_FINKEN_WA_BOUNCE TRUE
#endif
#ifndef TWINSWARM_FINKEN_WA_BOUNCE_DIST
#define TWINSWARM_FINKEN_WA_BOUNCE_DIST TWINSWARM_FINKEN_WA_GOAL_DIST
#endif

/* keep the last sighting (not in the firmware; 0: off): a reading nearer than the goal
 * distance stands in for later, farther ones this long, s. Four 30° cones leave diagonal gaps:
 * a copter that drifts out of a cone is still there, but the firmware's balance, seeing the far
 * wall instead, flies back towards it. */
#ifndef TWINSWARM_FINKEN_WA_SIGHTING_HOLD
#define TWINSWARM_FINKEN_WA_SIGHTING_HOLD 0.f
#endif

#define FILTER_MAX_LEN 8

/* ---- state ---- */

float twinswarm_sonar_real_m[4] = {NAN, NAN, NAN, NAN};
float twinswarm_sonar_virtual_m[4] = {NAN, NAN, NAN, NAN};
float twinswarm_sonar_fused_m[4] = {NAN, NAN, NAN, NAN};
float twinswarm_sonar_filtered_m[4] = {0.f, 0.f, 0.f, 0.f};
float twinswarm_ir_height_m = NAN;
float twinswarm_wall_avoid_roll = 0.f;
float twinswarm_wall_avoid_pitch = 0.f;
float twinswarm_wall_avoid_ll_roll = 0.f;
float twinswarm_wall_avoid_ll_pitch = 0.f;

float twinswarm_wa_cruise_fwd = TWINSWARM_FINKEN_WA_CRUISE_FWD;
float twinswarm_wa_cruise_right = TWINSWARM_FINKEN_WA_CRUISE_RIGHT;
uint8_t twinswarm_wa_bounce = TWINSWARM_FINKEN_WA_BOUNCE;
float twinswarm_wa_goal_dist = TWINSWARM_FINKEN_WA_GOAL_DIST;
float twinswarm_virtual_timeout = TWINSWARM_FINKEN_VIRTUAL_TIMEOUT;

static float virtual_raw_m[4] = {NAN, NAN, NAN, NAN};  /* as last received */
static float virtual_time_s = -1.f;                     /* sys_time of the last SONAR_UPLINK */
static uint16_t uplinks = 0;

static float history[4][FILTER_MAX_LEN];
static uint8_t history_len[4], history_at[4];
static float diff_m[2];         /* x, y */
static float error_k1_m[2];     /* lead-lag's last input */
static float out_k1_deg[2];     /* lead-lag's last output */
static float cruise_sign[2] = {1.f, 1.f};  /* fwd, right: flipped by bounces */
static uint32_t calls = 0;
static float sighting_m[4] = {NAN, NAN, NAN, NAN};  /* last reading nearer than the goal */
static float sighting_time_s[4] = {-1.f, -1.f, -1.f, -1.f};

static inline float clampf(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

/** NaN (nothing) as +inf, for min() */
static inline float far_if_nan(float v) { return isnan(v) ? INFINITY : v; }

/* ---- firmware sonar filter and lead-lag ---- */

/** a reading, or the last sighting where that was nearer and is recent enough */
static float with_sighting(int k, float reading_m, float now)
{
  float hold = TWINSWARM_FINKEN_WA_SIGHTING_HOLD;
  if (hold <= 0.f) { return reading_m; }
  if (!isnan(reading_m) && reading_m < twinswarm_wa_goal_dist) {
    sighting_m[k] = reading_m;
    sighting_time_s[k] = now;
    return reading_m;
  }
  bool recent = sighting_time_s[k] >= 0.f && now - sighting_time_s[k] <= hold;
  return recent ? sighting_m[k] : reading_m;
}

static void filter_push(int k, float reading_m)
{
  int len = TWINSWARM_FINKEN_WA_FILTER_LEN;
  if (len < 1) { len = 1; }
  if (len > FILTER_MAX_LEN) { len = FILTER_MAX_LEN; }
  /* no echo: the far clamp (the sonar reads its maximum) */
  float r = isnan(reading_m) ? TWINSWARM_FINKEN_WA_FILTER_MAX : reading_m;
  int at = history_at[k] % len;
  history[k][at] = clampf(r, TWINSWARM_FINKEN_WA_FILTER_MIN, TWINSWARM_FINKEN_WA_FILTER_MAX);
  history_at[k] = (at + 1) % len;
  if (history_len[k] < len) { history_len[k]++; }
  float s = 0.f;
  for (int i = 0; i < history_len[k]; i++) { s += history[k][i]; }
  twinswarm_sonar_filtered_m[k] = s / history_len[k];
  float g = twinswarm_wa_goal_dist;
  const float *f = twinswarm_sonar_filtered_m;
  diff_m[0] = fminf(f[TWINSWARM_BACK], g) - fminf(f[TWINSWARM_FRONT], g);
  diff_m[1] = fminf(f[TWINSWARM_RIGHT], g) - fminf(f[TWINSWARM_LEFT], g);
}

static bool filter_ready(void)
{
  return history_len[0] && history_len[1] && history_len[2] && history_len[3];
}

static void lead_lag(float t)
{
  const float t1 = TWINSWARM_FINKEN_WA_CONTROL_DELAY_TIME;
  const float tv = TWINSWARM_FINKEN_WA_CONTROL_HOLD_TIME;
  const float kp = TWINSWARM_FINKEN_WA_CONTROL_GAIN;
  const float a0 = (t - 2.f * t1) / (t + 2.f * t1);
  const float b0 = kp * (t - 2.f * tv) / (t + 2.f * t1);
  const float b1 = kp * (t + 2.f * tv) / (t + 2.f * t1);
  const float max = TWINSWARM_FINKEN_WA_MAX_CONTROL;
  for (int axis = 0; axis < 2; axis++) {
    float e = diff_m[axis];
    float u = clampf(-a0 * out_k1_deg[axis] + b1 * e + b0 * error_k1_m[axis], -max, max);
    out_k1_deg[axis] = u;
    error_k1_m[axis] = e;
  }
  /* x > 0: the front is closer than the back: nose up (Paparazzi pitch > 0) backs off;
   * y < 0: the right is closer: roll left (< 0) */
  twinswarm_wall_avoid_ll_pitch = out_k1_deg[0];
  twinswarm_wall_avoid_ll_roll = out_k1_deg[1];
}

/** the firmware's scaling of a pilot input towards an obstacle d away (filtered, m) */
static float pilot_scale(float d)
{
  float span = twinswarm_wa_goal_dist - TWINSWARM_FINKEN_WA_GUARD_DIST;
  if (span < 1e-3f) { span = 1e-3f; }
  return clampf((d - TWINSWARM_FINKEN_WA_GUARD_DIST) / span, 0.f, 1.f);
}

/** one cruise component: magnitude*sign towards `ahead` (if > 0) or `behind`, bounce, scale */
static float cruise(int axis, float setting, float ahead, float behind)
{
  if (!filter_ready()) { return setting * cruise_sign[axis]; }
  float c = setting * cruise_sign[axis];
  if (twinswarm_wa_bounce && c != 0.f) {
    float towards = c > 0.f ? ahead : behind;
    float away = c > 0.f ? behind : ahead;
    if (towards < TWINSWARM_FINKEN_WA_BOUNCE_DIST && away > towards) {
      cruise_sign[axis] = -cruise_sign[axis];
      c = -c;
    }
  }
  return c * pilot_scale(c > 0.f ? ahead : behind);
}

/* ---- telemetry ---- */

#if PERIODIC_TELEMETRY
static inline float tm(float v) { return isnan(v) ? -1.f : v; }

static void send_twinswarm_sonar(struct transport_tx *trans, struct link_device *dev)
{
  float r[4], v[4], f[4];
  for (int k = 0; k < 4; k++) {
    r[k] = tm(twinswarm_sonar_real_m[k]);
    v[k] = tm(twinswarm_sonar_virtual_m[k]);
    f[k] = tm(twinswarm_sonar_fused_m[k]);
  }
  float ir = tm(twinswarm_ir_height_m);
  float age = virtual_time_s < 0.f ? -1.f : get_sys_time_float() - virtual_time_s;
  pprz_msg_send_TWINSWARM_SONAR(trans, dev, AC_ID,
                                &r[0], &r[1], &r[2], &r[3],
                                &v[0], &v[1], &v[2], &v[3],
                                &f[0], &f[1], &f[2], &f[3],
                                &ir, &age,
                                &twinswarm_wall_avoid_roll, &twinswarm_wall_avoid_pitch,
                                &twinswarm_wall_avoid_ll_roll, &twinswarm_wall_avoid_ll_pitch,
                                &uplinks);
}
#endif

/* ---- module functions ---- */

void twinswarm_finken_init(void)
{
  for (int k = 0; k < 4; k++) {
    history_len[k] = history_at[k] = 0;
    twinswarm_sonar_filtered_m[k] = 0.f;
    sighting_m[k] = NAN;
    sighting_time_s[k] = -1.f;
  }
  diff_m[0] = diff_m[1] = 0.f;
  error_k1_m[0] = error_k1_m[1] = 0.f;
  out_k1_deg[0] = out_k1_deg[1] = 0.f;
#if PERIODIC_TELEMETRY
  register_periodic_telemetry(DefaultPeriodic, PPRZ_MSG_ID_TWINSWARM_SONAR, send_twinswarm_sonar);
#endif
}

void twinswarm_finken_parse_SONAR_UPLINK(uint8_t *buf)
{
  if (DL_SONAR_UPLINK_ac_id(buf) != AC_ID) { return; }
  /* the message's order is front, LEFT, back, RIGHT */
  uint16_t cm[4];
  cm[TWINSWARM_FRONT] = DL_SONAR_UPLINK_front(buf);
  cm[TWINSWARM_LEFT] = DL_SONAR_UPLINK_left(buf);
  cm[TWINSWARM_BACK] = DL_SONAR_UPLINK_back(buf);
  cm[TWINSWARM_RIGHT] = DL_SONAR_UPLINK_right(buf);
  for (int k = 0; k < 4; k++) {
    virtual_raw_m[k] = (cm[k] == 0 || cm[k] >= TWINSWARM_FINKEN_VIRTUAL_NONE_CM) ? NAN : cm[k] / 100.f;
  }
  virtual_time_s = get_sys_time_float();
  uplinks++;
}

void twinswarm_finken_periodic(void)
{
  const float now = get_sys_time_float();

  /* real sensors */
#ifdef USE_NPS
  for (int k = 0; k < 4; k++) {
    float s = twinswarm_sonar_m[k];
    twinswarm_sonar_real_m[k] = (isfinite(s) && s > 0.f) ? s : NAN;
  }
  twinswarm_ir_height_m = isfinite(twinswarm_ir_m) ? twinswarm_ir_m : NAN;
#endif
  if (!isnan(twinswarm_ir_height_m)) {
    AbiSendMsgAGL(TWINSWARM_FINKEN_IR_AGL_ID, get_sys_time_usec(), twinswarm_ir_height_m);
  }

  /* fusion with the virtual readings */
  bool fresh = virtual_time_s >= 0.f && now - virtual_time_s <= twinswarm_virtual_timeout;
  for (int k = 0; k < 4; k++) {
    twinswarm_sonar_virtual_m[k] = fresh ? virtual_raw_m[k] : NAN;
    float m = fminf(far_if_nan(twinswarm_sonar_real_m[k]), far_if_nan(twinswarm_sonar_virtual_m[k]));
    twinswarm_sonar_fused_m[k] = isinf(m) ? NAN : m;
  }

  /* the firmware's sonar filter: one sonar per update, round robin, or all four */
#if TWINSWARM_FINKEN_SONAR_ROUND_ROBIN
  int k = calls % 4;
  filter_push(k, with_sighting(k, twinswarm_sonar_fused_m[k], now));
#else
  for (int k = 0; k < 4; k++) { filter_push(k, with_sighting(k, twinswarm_sonar_fused_m[k], now)); }
#endif

  /* the lead-lag at its own rate */
  uint32_t every = (uint32_t)lroundf(TWINSWARM_FINKEN_SONAR_FREQ / TWINSWARM_FINKEN_WA_UPDATE_FREQ);
  if (every < 1) { every = 1; }
  calls++;
  if (filter_ready() && calls % every == 0) {
    lead_lag(every / TWINSWARM_FINKEN_SONAR_FREQ);
  }

  /* output: lead-lag plus cruise (forward = nose down = negative Paparazzi pitch) */
  const float *f = twinswarm_sonar_filtered_m;
  float fwd = cruise(0, twinswarm_wa_cruise_fwd, f[TWINSWARM_FRONT], f[TWINSWARM_BACK]);
  float right = cruise(1, twinswarm_wa_cruise_right, f[TWINSWARM_RIGHT], f[TWINSWARM_LEFT]);
  twinswarm_wall_avoid_pitch = twinswarm_wall_avoid_ll_pitch - fwd;
  twinswarm_wall_avoid_roll = twinswarm_wall_avoid_ll_roll + right;
}
