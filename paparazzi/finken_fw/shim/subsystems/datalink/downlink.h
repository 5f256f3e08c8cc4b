/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SUBSYSTEMS_DOWNLINK_H
#define FINKEN_V5_SUBSYSTEMS_DOWNLINK_H
#include "finken_v5_compat.h"
#endif
