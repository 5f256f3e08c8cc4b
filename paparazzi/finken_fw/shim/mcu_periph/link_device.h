/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_LINK_DEVICE_H
#define FINKEN_V5_LINK_DEVICE_H
#include "pprzlink/pprzlink_device.h"
#endif
