/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_COMMON_FLIGHT_PLAN_H
#define FINKEN_V5_COMMON_FLIGHT_PLAN_H
#include "modules/nav/common_flight_plan.h"   /* stage_time, block_time */
#endif
