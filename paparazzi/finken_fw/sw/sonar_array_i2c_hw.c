/*
 * This file is part of Twinswarm's Paparazzi bindings (GPL v2 or later).
 *
 * Compiles the firmware's sonar_array_i2c.c unchanged (the copy on the include path:
 * -I.../finken_fw/<version>), with SITL undefined for this one file: its periodic function
 * has the real I2C round robin under #ifndef SITL and, under #else, `#warn`, which is not a
 * C preprocessor directive (a hard error with NPS's -DSITL). The copter in NPS runs the
 * hardware path, against the I2C bus of finken_fw_nps.c.
 */
#undef SITL
#include "modules/sonar/sonar_array_i2c.c"
