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
#include <stdio.h>
#include <stdlib.h>

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
  static uint32_t next_ms = 0;
  if (on < 0) { on = getenv("FINKEN_FW_DEBUG") != NULL; }
  if (!on || get_sys_time_msec() < next_ms) { return; }
  next_ms = get_sys_time_msec() + 1000;
  fprintf(stderr, "[finken_fw] t=%.1f sonar_cm=%u,%u,%u,%u filt_cm=%d,%d,%d,%d world_m=%.2f,%.2f,%.2f,%.2f "
          "ir=%u->%.3f (world %.3f) z=%.3f sp_z=%.2f ctl=%d thrust=%.3f pitch=%.2f roll=%.2f motors=%d\n",
          get_sys_time_float(), sonar_values.front, sonar_values.right, sonar_values.back, sonar_values.left,
          finken_sensor_model.distance_d_front, finken_sensor_model.distance_d_right,
          finken_sensor_model.distance_d_back, finken_sensor_model.distance_d_left,
          twinswarm_sonar_m[0], twinswarm_sonar_m[1], twinswarm_sonar_m[2], twinswarm_sonar_m[3],
          ir_measurement, ir_distance, twinswarm_ir_m, POS_FLOAT_OF_BFP(finken_sensor_model.pos.z),
          finken_system_set_point.z, finken_system_model_control_height, finken_actuators_set_point.thrust,
          finken_actuators_set_point.pitch, finken_actuators_set_point.roll, autopilot_get_motors_on());
}

void finken_fw_nps_periodic(void)
{
  debug_print();
  hook_bus();   /* cheap; also covers an i2c init that ran after this module's */
  fill_ir();
  finken_v5_imu.gyro = imu.gyros[0].scaled;
  finken_v5_imu.accel = imu.accels[0].scaled;
  finken_v5_imu.mag = imu.mags[0].scaled;
  sensor_filtered.acceleration = imu.accels[0].scaled;
  sensor_filtered.rates = imu.gyros[0].scaled;
  if (!armed && stateIsAttitudeValid() && autopilot_get_mode() == AP_MODE_NAV) {
    autopilot_set_motors_on(true);   /* the pilot's kill switch */
    armed = autopilot_get_motors_on();
  }
}
