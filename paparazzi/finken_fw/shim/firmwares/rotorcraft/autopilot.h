/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_ROTORCRAFT_AUTOPILOT_H
#define FINKEN_V5_ROTORCRAFT_AUTOPILOT_H
#include "autopilot.h"
/* v5's global autopilot_mode (2015-07 finken_model_system.c reads it) is v6.4's autopilot.mode */
#ifndef autopilot_mode
#define autopilot_mode autopilot_get_mode()
#endif
#endif
