/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SUBSYSTEMS_ELECTRICAL_H
#define FINKEN_V5_SUBSYSTEMS_ELECTRICAL_H
#include "modules/energy/electrical.h"
#endif
