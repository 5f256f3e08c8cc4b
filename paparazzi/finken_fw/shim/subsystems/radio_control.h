/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SUBSYSTEMS_RADIO_CONTROL_H
#define FINKEN_V5_SUBSYSTEMS_RADIO_CONTROL_H
#include "modules/radio_control/radio_control.h"
#endif
