/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_DL_PROTOCOL_H
#define FINKEN_V5_DL_PROTOCOL_H
/* v5's generated datalink macros (DL_SONAR_UPLINK_front(dl_buffer), ...): pprzlink's, generated
   from the merged messages.xml (SONAR_UPLINK = datalink 153, the firmware's fields); v5's global
   dl_buffer is v6.4's (finken_fw_nps_sonar_uplink() hands the message to it) */
#include "pprzlink/dl_protocol.h"
#include "modules/datalink/datalink.h"
#endif
