/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SUBSYSTEMS_TRANSPORT_H
#define FINKEN_V5_SUBSYSTEMS_TRANSPORT_H
#include "finken_v5_compat.h"
#include "pprzlink/pprzlink_transport.h"
#endif
