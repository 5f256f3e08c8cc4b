/* Twinswarm (GPL v2 or later): v5 header name for the FINken firmware, see finken_v5_compat.h */
#ifndef FINKEN_V5_SPEKTRUM_ARCH_H
#define FINKEN_V5_SPEKTRUM_ARCH_H
/* the lab's board header (STM32 Spektrum receiver): nothing of it is used by finken_model_system.c */
#endif
