/*
 * This file is part of Twinswarm's Paparazzi bindings (GPL v2 or later).
 *
 * The FINken firmware's hardware edge in NPS: see finken_fw_nps.h.
 */
#include "modules/finken_fw/finken_fw_nps.h"

#include <math.h>

#include "generated/airframe.h"
#include "autopilot.h"
#include "state.h"
#include "mcu_periph/i2c.h"
#include "mcu_periph/adc.h"
#include "modules/energy/electrical.h"
#include "nps_electrical.h"
#include "nps_fdm_twinswarm.h"
#include "nps_fdm.h"
#include "nps_sensors.h"
#if FINKEN_FW_VERSION == 201507
#include "modules/ahrs/ahrs_int_cmpl_quat.h"   /* quadrotor_lia_ovgu.xml: int_cmpl_quat */
#else
#include "modules/ahrs/ahrs_float_cmpl.h"      /* fink3.xml: float_cmpl_quat */
#endif
#include "modules/actuators/motor_mixing.h"
#include "firmwares/rotorcraft/stabilization.h"
/* the v5 names the firmware reads (shim headers); then back to v6.4's imu */
#include "subsystems/imu.h"
#include "modules/sensor_filter/sensor_filter.h"
#include "finken_v5_compat.h"
#undef imu
/* the firmware's state, for the FINKEN_FW_DEBUG print */
#include "modules/sonar/sonar_array_i2c.h"
#include "modules/finken_model/finken_model_sensors.h"
#include "modules/finken_model/finken_model_system.h"
#include "modules/finken_model/finken_model_actuators.h"
#include "modules/finken_ir_adc/finken_ir_adc.h"
#if FINKEN_FW_VERSION == 201507
#include "modules/finken_model/finken_model_environment.h"
#include "dl_protocol.h"
#include "modules/nav/common_flight_plan.h"
#endif
#include <stdio.h>
#include <string.h>
#include <stdlib.h>

#ifndef FINKEN_FW_VERSION
#error "FINKEN_FW_VERSION: 201512 or 201507, set by the module"
#endif
#ifndef SONAR_I2C_DEV
#error "SONAR_I2C_DEV: the firmware's sonar bus (fink3.xml: i2c1), set by the module"
#endif
#ifndef ADC_CHANNEL_IR
#error "ADC_CHANNEL_IR: the firmware's IR ADC channel, set by the module"
#endif

/** SRF02 addresses of sonar_array_i2c (front, right, back, left = 0x71..0x74, its defaults) */
#define FINKEN_FW_SRF_ADDR_FIRST 0x71
#define FINKEN_FW_SRF_N 4
/** SRF02 command register value 81: range in cm */
#define FINKEN_FW_SRF_RANGE_CM 81

struct finken_v5_imu_s finken_v5_imu;
bool kill_throttle = false;
uint16_t autopilot_flight_time = 0;
struct finken_v5_sensor_filter_s sensor_filtered;
uint16_t finken_fw_nps_ir_count;
float finken_fw_nps_ir_m = NAN;

static float srf_latched_m[FINKEN_FW_SRF_N] = {NAN, NAN, NAN, NAN};
static struct adc_buf *ir_buf = NULL;
static bool armed = false;

/* ---- sonars: the I2C bus ---- */

static uint16_t srf_cm(float m)
{
  if (!(m > 0.f)) { return 0; }            /* NaN (no echo) or nothing: the SRF02 reads 0 */
  float cm = roundf(m * 100.f);
  return cm > 65535.f ? 65535 : (uint16_t)cm;
}

static bool finken_fw_i2c_submit(struct i2c_periph *p __attribute__((unused)), struct i2c_transaction *t)
{
  int k = (int)(t->slave_addr >> 1) - FINKEN_FW_SRF_ADDR_FIRST;
  if (k < 0 || k >= FINKEN_FW_SRF_N) {
    t->status = I2CTransFailed;            /* nothing else on the lab's sonar bus */
    return true;
  }
  if (t->type == I2CTransTx && t->len_w >= 1 && t->buf[0] == FINKEN_FW_SRF_RANGE_CM) {
    /* the ranging command: the sonar measures now */
    srf_latched_m[k] = twinswarm_sonar_m[k];
  } else if (t->type == I2CTransRx && t->len_r >= 2) {
    /* the read of the range registers (high byte first) */
    uint16_t cm = srf_cm(srf_latched_m[k]);
    t->buf[0] = (uint8_t)(cm >> 8);
    t->buf[1] = (uint8_t)(cm & 0xff);
  }
  t->status = I2CTransSuccess;
  return true;
}

/* ---- IR: the ADC buffer ---- */

/* The firmware's table (finken_ir_adc.c, ir_in_samples / ir_out_samples: ADC counts to m),
 * copied here to invert it. */
#define FW_IR_N 6
static const uint16_t fw_ir_in[FW_IR_N] = {800, 830, 900, 1150, 1650, 2700};
static const float fw_ir_out[FW_IR_N] = {1.30, 1.00, .80, .60, .40, .20};

uint16_t finken_fw_ir_count_of_distance(float d)
{
  if (!(d == d)) { return 0; }             /* NaN: nothing in range, reads as the far end */
  if (d >= fw_ir_out[0]) { return fw_ir_in[0]; }
  if (d <= fw_ir_out[FW_IR_N - 1]) { return fw_ir_in[FW_IR_N - 1]; }
  for (int i = 1; i < FW_IR_N; i++) {
    if (d >= fw_ir_out[i]) {
      float w = (fw_ir_out[i - 1] - d) / (fw_ir_out[i - 1] - fw_ir_out[i]);
      return (uint16_t)lroundf(fw_ir_in[i - 1] + w * (fw_ir_in[i] - fw_ir_in[i - 1]));
    }
  }
  return fw_ir_in[FW_IR_N - 1];
}

void __real_adc_buf_channel(uint8_t adc_channel, struct adc_buf *s, uint8_t av_nb_sample);
void __wrap_adc_buf_channel(uint8_t adc_channel, struct adc_buf *s, uint8_t av_nb_sample);
void __wrap_adc_buf_channel(uint8_t adc_channel, struct adc_buf *s, uint8_t av_nb_sample)
{
  if (adc_channel == ADC_CHANNEL_IR && s != NULL) {
    ir_buf = s;
    s->av_nb_sample = av_nb_sample > 0 ? av_nb_sample : 1;
    s->head = 0;
    finken_fw_nps_ir_count = finken_fw_ir_count_of_distance(twinswarm_ir_m);
    s->sum = (uint32_t)finken_fw_nps_ir_count * s->av_nb_sample;
    return;
  }
  __real_adc_buf_channel(adc_channel, s, av_nb_sample);
}

static void fill_ir(void)
{
  if (ir_buf == NULL) { return; }
  finken_fw_nps_ir_m = twinswarm_ir_m;
  finken_fw_nps_ir_count = finken_fw_ir_count_of_distance(twinswarm_ir_m);
  for (int i = 0; i < ir_buf->av_nb_sample && i < MAX_AV_NB_SAMPLE; i++) {
    ir_buf->values[i] = finken_fw_nps_ir_count;
  }
  ir_buf->sum = (uint32_t)finken_fw_nps_ir_count * ir_buf->av_nb_sample;
}

/* ---- telemetry registered by name (v5) ---- */

int8_t finken_v5_register_periodic_telemetry(void *pt __attribute__((unused)),
    const char *name __attribute__((unused)), telemetry_cb cb __attribute__((unused)))
{
  return -1;   /* the firmware's messages are not in v6.4's messages.xml */
}

/* ---- the uplink (2015-07): finken_model.xml's datalink function reads v5's dl_buffer ---- */

void finken_fw_nps_sonar_uplink(uint8_t *buf __attribute__((unused)))
{
#if FINKEN_FW_VERSION == 201507
  if (buf != dl_buffer) {
    memcpy(dl_buffer, buf, MSG_SIZE);
  }
  finken_sensor_model_receive();
#endif
}

/* ---- module ---- */

static void hook_bus(void)
{
  SONAR_I2C_DEV.submit = finken_fw_i2c_submit;
}

void finken_fw_nps_init(void)
{
  hook_bus();
  /* v5 decivolts for the firmware (see finken_fw_nps.h) */
#ifdef MAX_BAT_LEVEL
  nps_electrical.supply_voltage = 10. * MAX_BAT_LEVEL;
#else
  nps_electrical.supply_voltage = 111.;
#endif
  electrical.vsupply = nps_electrical.supply_voltage;
}

/* FINKEN_FW_DEBUG=1 in the environment: once per simulated second, what the firmware read and
 * commanded, on stderr */
static void debug_print(void)
{
  static int on = -1;
  static uint32_t next_ms = 0, period_ms = 1000;
  if (on < 0) {
    const char *v = getenv("FINKEN_FW_DEBUG");
    on = v != NULL;
    if (on && atoi(v) >= 10) { period_ms = (uint32_t)atoi(v); }
  }
  if (!on || get_sys_time_msec() < next_ms) { return; }
  next_ms = get_sys_time_msec() + period_ms;
#if FINKEN_FW_VERSION == 201507
  fprintf(stderr, "[finken_fw] t=%.1f sonar_cm=%u,%u,%u,%u remote_cm=%u,%u,%u,%u fused_cm=%d,%d,%d,%d "
          "world_m=%.2f,%.2f,%.2f,%.2f ir=%u->%.3f eq %.3f (world %.3f) sp_z=%.2f thrust_sp=%.3f thrust=%.3f "
          "alpha=%.2f beta=%.2f block=%u stage=%u/%u motors=%d\n",
          get_sys_time_float(), sonar_values.front, sonar_values.right, sonar_values.back, sonar_values.left,
          finken_sensor_model.remote_d_front, finken_sensor_model.remote_d_right,
          finken_sensor_model.remote_d_back, finken_sensor_model.remote_d_left,
          finken_sensor_model.distance_d_front, finken_sensor_model.distance_d_right,
          finken_sensor_model.distance_d_back, finken_sensor_model.distance_d_left,
          twinswarm_sonar_m[0], twinswarm_sonar_m[1], twinswarm_sonar_m[2], twinswarm_sonar_m[3],
          ir_measurement, ir_distance, ir_distance_equalized, twinswarm_ir_m, finken_system_set_point.distance_z,
          finken_actuators_set_point.thrust, finken_actuators_model.thrust, finken_actuators_set_point.alpha,
          finken_actuators_set_point.beta, (unsigned)nav_block, (unsigned)nav_stage, (unsigned)stage_time, autopilot_get_motors_on());
#else
  fprintf(stderr, "[finken_fw] t=%.1f sonar_cm=%u,%u,%u,%u filt_cm=%d,%d,%d,%d world_m=%.2f,%.2f,%.2f,%.2f "
          "ir=%u->%.3f (world %.3f) z=%.3f sp_z=%.2f ctl=%d thrust=%.3f pitch=%.2f roll=%.2f motors=%d\n",
          get_sys_time_float(), sonar_values.front, sonar_values.right, sonar_values.back, sonar_values.left,
          finken_sensor_model.distance_d_front, finken_sensor_model.distance_d_right,
          finken_sensor_model.distance_d_back, finken_sensor_model.distance_d_left,
          twinswarm_sonar_m[0], twinswarm_sonar_m[1], twinswarm_sonar_m[2], twinswarm_sonar_m[3],
          ir_measurement, ir_distance, twinswarm_ir_m, POS_FLOAT_OF_BFP(finken_sensor_model.pos.z),
          finken_system_set_point.z, finken_system_model_control_height, finken_actuators_set_point.thrust,
          finken_actuators_set_point.pitch, finken_actuators_set_point.roll, autopilot_get_motors_on());
#endif
  struct FloatEulers *e = stateGetNedToBodyEulers_f();
#if FINKEN_FW_VERSION == 201507
  struct FloatRates est_bias;
  RATES_FLOAT_OF_BFP(est_bias, ahrs_icq.gyro_bias);
#else
  struct FloatRates est_bias = ahrs_fc.gyro_bias;
#endif
  fprintf(stderr, "[finken_fw_att] t=%.3f est_deg=%.3f,%.3f,%.3f true_deg=%.3f,%.3f,%.3f "
          "est_bias_dps=%.4f,%.4f,%.4f nps_bias_dps=%.4f,%.4f,%.4f acc=%.3f,%.3f,%.3f vel=%.3f,%.3f pos=%.2f,%.2f agl=%.3f mix=%d,%d,%d,%d cmd=%d,%d,%d,%d\n",
          get_sys_time_float(), DegOfRad(e->phi), DegOfRad(e->theta), DegOfRad(e->psi),
          DegOfRad(fdm.ltp_to_body_eulers.phi), DegOfRad(fdm.ltp_to_body_eulers.theta), DegOfRad(fdm.ltp_to_body_eulers.psi),
          DegOfRad(est_bias.p), DegOfRad(est_bias.q), DegOfRad(est_bias.r),
          DegOfRad(sensors.gyro.bias_random_walk_value.x), DegOfRad(sensors.gyro.bias_random_walk_value.y),
          DegOfRad(sensors.gyro.bias_random_walk_value.z),
          fdm.body_accel.x, fdm.body_accel.y, fdm.body_accel.z, fdm.ltp_ecef_vel.x, fdm.ltp_ecef_vel.y,
          fdm.ltpprz_pos.x, fdm.ltpprz_pos.y, fdm.agl, motor_mixing.commands[0], motor_mixing.commands[1],
          motor_mixing.commands[2], motor_mixing.commands[3], stabilization_cmd[COMMAND_ROLL],
          stabilization_cmd[COMMAND_PITCH], stabilization_cmd[COMMAND_YAW], stabilization_cmd[COMMAND_THRUST]);
}

/* The copter's IMU calibration (fink3.xml includes calib/$AC_ID_imu_calib.xml, which is not among
 * the copies): FINKEN_FW_IMU_TRIM="PHI,THETA" (deg) sets the autopilot's body-to-IMU angles, as
 * the lab's per-copter calibration file did (aircraft 5, Dec 2015: THETA -2.5). Set at run time,
 * before the AHRS aligns: NPS's simulated IMU keeps its own mounting (the airframe's, 0: the
 * world's copter has none), so this is a calibration of the autopilot, not of the physics. */
static void apply_imu_trim(void)
{
  const char *v = getenv("FINKEN_FW_IMU_TRIM");
  float phi = 0.f, theta = 0.f;
  if (v == NULL || sscanf(v, "%f,%f", &phi, &theta) != 2) { return; }
  imu_SetBodyToImuPhi(RadOfDeg(phi));
  imu_SetBodyToImuTheta(RadOfDeg(theta));
  fprintf(stderr, "[finken_fw] IMU calibration: body to IMU phi %.3f theta %.3f deg (FINKEN_FW_IMU_TRIM)\n",
          phi, theta);
}

void finken_fw_nps_periodic(void)
{
  static bool trimmed = false;
  if (!trimmed) {
    apply_imu_trim();
    trimmed = true;
  }
  debug_print();
  hook_bus();   /* cheap; also covers an i2c init that ran after this module's */
  fill_ir();
  finken_v5_imu.gyro = imu.gyros[0].scaled;
  finken_v5_imu.accel = imu.accels[0].scaled;
  finken_v5_imu.mag = imu.mags[0].scaled;
  sensor_filtered.acceleration = imu.accels[0].scaled;
  sensor_filtered.rates = imu.gyros[0].scaled;
#if FINKEN_FW_VERSION == 201507
  /* The paper's plan (ovgu_sonar.xml) starts with its Takeoff block (the GCS strip button): the
   * operator armed once the AHRS had aligned, then pressed Takeoff. NPS starts the plan at once,
   * so the glue arms when the AHRS is aligned and then restarts the plan's first block. */
  if (!armed && ahrs_icq.is_aligned && autopilot_get_mode() == AP_MODE_NAV) {
    autopilot_set_motors_on(true);   /* the pilot's kill switch */
    armed = autopilot_get_motors_on();
    if (armed) {
      nav_goto_block(0);             /* the operator's Takeoff */
    }
  }
#else
  if (!armed && stateIsAttitudeValid() && autopilot_get_mode() == AP_MODE_NAV) {
    autopilot_set_motors_on(true);   /* the pilot's kill switch */
    armed = autopilot_get_motors_on();
  }
#endif
}
