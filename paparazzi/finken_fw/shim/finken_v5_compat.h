/*
 * This file is part of Twinswarm's Paparazzi bindings (GPL v2 or later).
 *
 * Paparazzi v5 -> v6.4 interface bridge for the FINken firmware's own modules
 * (shared/paparazzi/finken_firmware, compiled unchanged). Included by every v5 header name
 * this folder provides (subsystems/..., messages.h, ...), which v6.4 no longer has.
 *
 *  - bool_t (v5 std.h) is C99 bool;
 *  - register_periodic_telemetry(pt, "NAME", cb): v5 registered by message NAME, v6.4 by
 *    numeric id; the firmware's messages (FINKEN_*, HC_DEBUG, SONAR_ARRAY) are not in v6.4's
 *    messages.xml, so the registration is accepted (finken_fw_nps.c) and nothing is sent;
 *  - DOWNLINK_SEND_<firmware message>(...): compiled out (same reason). The callbacks
 *    themselves compile as they are;
 *  - 2015-07: kill_throttle and autopilot_flight_time (v5 globals its flight plan sets).
 */
#ifndef FINKEN_V5_COMPAT_H
#define FINKEN_V5_COMPAT_H

#include <stdbool.h>
#include <string.h>
#include "std.h"
#include "mcu_periph/sys_time.h"
#include "modules/datalink/downlink.h"
#include "modules/datalink/telemetry.h"

typedef bool bool_t;

/* v5 registered periodic telemetry by message NAME, v6.4 by id. The macro picks by the type of
 * the second argument, so that v6.4 code that sees it (the firmware's headers are included by
 * the flight plan's header) still calls the real function. */
#include "modules/datalink/telemetry_common.h"
int8_t finken_v5_register_periodic_telemetry(void *pt, const char *name, telemetry_cb cb);
#undef register_periodic_telemetry
#define register_periodic_telemetry(_pt, _id, _cb) _Generic((_id), \
    char *: finken_v5_register_periodic_telemetry, \
    const char *: finken_v5_register_periodic_telemetry, \
    default: register_periodic_telemetry)(_pt, _id, _cb)

#undef DOWNLINK_SEND_FINKEN_SENSOR_MODEL
#undef DOWNLINK_SEND_HC_DEBUG
#undef DOWNLINK_SEND_FINKEN_SYSTEM_SET_POINT
#undef DOWNLINK_SEND_FINKEN_ACTUATORS_MODEL
#undef DOWNLINK_SEND_FINKEN_ACTUATORS_SET_POINT
#undef DOWNLINK_SEND_FINKEN_IR_ADC
#undef DOWNLINK_SEND_SONAR_ARRAY
#undef DOWNLINK_SEND_FINKEN_WALL_AVOID
#undef DOWNLINK_SEND_FINKEN_SYSTEM_MODEL
#undef DOWNLINK_SEND_FINKEN_ENVIRONMENT_MODEL
#undef DOWNLINK_SEND_SONAR_DEBUG
#define DOWNLINK_SEND_FINKEN_SENSOR_MODEL(...) {}
#define DOWNLINK_SEND_HC_DEBUG(...) {}
#define DOWNLINK_SEND_FINKEN_SYSTEM_SET_POINT(...) {}
#define DOWNLINK_SEND_FINKEN_ACTUATORS_MODEL(...) {}
#define DOWNLINK_SEND_FINKEN_ACTUATORS_SET_POINT(...) {}
#define DOWNLINK_SEND_FINKEN_IR_ADC(...) {}
#define DOWNLINK_SEND_SONAR_ARRAY(...) {}
#define DOWNLINK_SEND_FINKEN_WALL_AVOID(...) {}
#define DOWNLINK_SEND_FINKEN_SYSTEM_MODEL(...) {}
#define DOWNLINK_SEND_FINKEN_ENVIRONMENT_MODEL(...) {}
#define DOWNLINK_SEND_SONAR_DEBUG(...) {}

/* v5 rotorcraft globals that the 2015-07 flight plan (ovgu_sonar.xml) sets at take-off:
 * kill_throttle (v6.4: autopilot.kill_throttle, which the glue's arming owns) and
 * autopilot_flight_time (v6.4: autopilot.flight_time). Stand-ins in finken_fw_nps.c: written by
 * the plan, read by nobody. */
extern bool kill_throttle;
extern uint16_t autopilot_flight_time;

#endif
