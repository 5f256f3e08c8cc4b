/*
 * Twinswarm flight model for Paparazzi NPS.
 *
 * This file is part of Twinswarm's Paparazzi bindings; like the Paparazzi code it is
 * built into, it is GPL (v2 or later).
 *
 * NPS's flight dynamics are computed by a Twinswarm world (or any server speaking the
 * protocol below) over one TCP connection on loopback, in lockstep: every NPS step sends
 * the motor commands and blocks until the world answers with the copter's state after
 * that step. Nothing here reads the wall clock; run NPS with a huge --time_factor (see
 * paparazzi/README.md) so that its main loop does not pace itself either, and the world
 * sets the pace.
 *
 * Address: env TWINSWARM_FDM="host:port" (TCP; default 127.0.0.1:7460) or "unix:PATH" (a
 * Unix-domain stream socket, where the world runs on the same machine: the same records, without
 * the loopback TCP stack's work on every one; `twinswarm run --autopilot-listen unix:PATH`).
 * Env TWINSWARM_FDM_AC_ID (speed benches only): the aircraft id this NPS says in its hello, i.e.
 * the copter it flies, instead of the compiled AC_ID, so that one build can fly many copters;
 * its telemetry and datalink stay the compiled AC_ID's (not for runs with Paparazzi's link).
 * Env TWINSWARM_FDM_CONNECT_TIMEOUT_S (default 30): how long to retry connecting.
 * Env TWINSWARM_FDM_VERBOSE=1: print every 1000th exchanged state.
 * Env TWINSWARM_NPS_REALTIME=1: let NPS's threads take the real-time policies they ask for
 * (SCHED_FIFO, which a process run as root gets); by default they stay where they are.
 *
 * Env TWINSWARM_FDM_UPLINK_TIMEOUT_S (default 5): how long an autopilot step waits for uplink
 * messages the world has counted (below) before NPS gives up with an error (exit status 3).
 *
 * Protocol v2, little-endian, fixed-size records, no padding (the world also takes v1 clients:
 * their state records end after `crashed`):
 *   hello, NPS -> world, once:  "TWFD" (4 bytes), u32 version = 2, u32 ac_id, f64 dt      (20 B)
 *   step,  NPS -> world:        u32 0x54575331, u64 step, u8 launch, u8 n = 4,
 *                               f64 commands[n] (motor_mixing.commands / MAX_PPRZ:
 *                               0..1 with motors on, -1 with motors stopped)           (46 B)
 *   state, world -> NPS:        u32 0x54575332, u64 step (echo), f64 t_s,
 *                               pos_ned[3], vel_ned[3], accel_ned[3] (kinematic, no g),
 *                               quat_ned_to_body[4] (w,x,y,z), body_rates[3] (p,q,r),
 *                               body_accel[3] (specific force, as an accelerometer reads),
 *                               agl_m, sonar_m[4] (front,right,back,left; NaN none),
 *                               ir_m (NaN none), u8 crashed,
 *                               u32 uplinks (v2; see "The uplink in the lockstep")     (225 B)
 * Step 0 is sent from nps_fdm_init() with zero commands and launch 0, so that NpsFdm is
 * filled before NPS's sensors initialise (as nps_fdm_pybullet does with a first step);
 * every later call of nps_fdm_run_step() sends step 1, 2, ...
 *   refused, world -> NPS:      u32 0x54575330, u16 n, n bytes of UTF-8 (in place of a state;
 *                               the world then closes): NPS prints why and exits with status 2
 * The world closing the connection ends NPS (exit status 0); a refusal (an ac_id that flies no
 * copter of the scene, another step rate, or a drop after a stall, e.g. SIGSTOP) exits with 2.
 *
 * The uplink in the lockstep (v2): the world sends the virtual-sonar uplink (SONAR_UPLINK, or
 * VIRTUAL_SONAR) over Ivy to Paparazzi's `link`, which forwards it over UDP to this aircraft's
 * datalink, at wall-clock times. `uplinks` in a state record is how many such messages for this
 * aircraft the world sent before that state; 0xFFFFFFFF: none are counted (no link in the run,
 * or an uplink the world does not send), the datalink runs as Paparazzi made it. Linked with
 * -Wl,--wrap=pprz_check_and_parse (conf/modules/fdm_twinswarm.xml, nps target), this file
 * stands between the datalink's UDP device and Paparazzi's own parsing (pprz_dl_event ->
 * DlCheckAndParse -> dl_parse_msg -> the modules' datalink functions): it takes every complete
 * frame out of the device into its own queue, and gives the autopilot, one per datalink event
 * as Paparazzi does, the counted ones only up to the count of the last state: at an event whose
 * count its datalink has not reached yet, it waits (TWINSWARM_FDM_UPLINK_TIMEOUT_S) until it
 * has; a counted message beyond the count is held for a later step. Counted first, then the
 * others (link's PING, a GCS's messages: not counted, given as they come). So each uplink
 * reaches the autopilot at the step the world named, whatever the wall clock did.
 *
 * Frames: the world's NED arena frame (origin at the arena centre on the floor, x north,
 * y east, z down) is NPS's LTP frame, placed at the flight plan's origin (NAV_LAT0,
 * NAV_LON0, ground at NAV_ALT0 above MSL), the origin the INS takes from the flight plan.
 */

#include "nps_fdm.h"
#include "nps_fdm_twinswarm.h"

#include <stdlib.h>
#include <stdio.h>
#include <string.h>
#include <errno.h>
#include <math.h>
#include <unistd.h>
#include <time.h>
#include <sys/types.h>
#include <sys/socket.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <arpa/inet.h>
#include <netdb.h>
#include <sys/un.h>
#include <sys/stat.h>
#include <poll.h>
#include <pthread.h>
#include <sched.h>

#include "math/pprz_geodetic.h"
#include "math/pprz_geodetic_double.h"
#include "math/pprz_algebra.h"
#include "math/pprz_algebra_double.h"
#include "math/pprz_isa.h"

#include "generated/airframe.h"
#include "generated/flight_plan.h"

#define TWFD_VERSION 2u
#define TWFD_MAGIC_STEP 0x54575331u   /* "TWS1" */
#define TWFD_MAGIC_STATE 0x54575332u  /* "TWS2" */
#define TWFD_MAGIC_REFUSED 0x54575330u  /* "TWS0": u16 n, n bytes of why; then the world closes */
#define TWFD_N_MOTORS 4
#define TWFD_HELLO_LEN 20
#define TWFD_STEP_LEN (4 + 8 + 1 + 1 + 8 * TWFD_N_MOTORS)
#define TWFD_STATE_NF 26
#define TWFD_STATE_LEN (4 + 8 + 8 * TWFD_STATE_NF + 1 + 4)
#define TWFD_UPLINKS_NOT_COUNTED 0xFFFFFFFFu

#ifndef AC_ID
#define AC_ID 0
#endif

#ifndef TWINSWARM_FDM_DEFAULT
#define TWINSWARM_FDM_DEFAULT "127.0.0.1:7460"
#endif

#ifndef TWINSWARM_FDM_TEMPERATURE
#define TWINSWARM_FDM_TEMPERATURE 20.0 /* indoor lab, deg C */
#endif

// NpsFdm structure
struct NpsFdm fdm;

float twinswarm_sonar_m[4] = {NAN, NAN, NAN, NAN};
float twinswarm_ir_m = NAN;
uint8_t twinswarm_crashed = 0;
double twinswarm_time_s = 0.;
uint64_t twinswarm_step = 0;

static struct LtpDef_d ltpdef;
static struct DoubleQuat ecef_to_ltp_quat;
static double ground_hmsl;       ///< height of the arena floor above MSL, m
static double temperature_c = TWINSWARM_FDM_TEMPERATURE;
static int sock = -1;
static int fdm_ac_id = AC_ID;    /* the copter flown: AC_ID, or TWINSWARM_FDM_AC_ID (benches) */
static uint64_t next_step = 0;
static bool have_state = false; /* a state has come: the world took this aircraft */
static bool verbose = false;
static struct DoubleRates last_rates;
static bool have_last_rates = false;
/* the uplink in the lockstep: the count of the last state record */
static uint32_t uplinks_named = TWFD_UPLINKS_NOT_COUNTED;
static void datalink_drain(void);
static void datalink_report(char *buf, size_t len);

/* little-endian encoding, independent of the host's byte order */
static void put_u32(uint8_t *b, uint32_t v) { for (int i = 0; i < 4; i++) { b[i] = (uint8_t)(v >> (8 * i)); } }
static void put_u64(uint8_t *b, uint64_t v) { for (int i = 0; i < 8; i++) { b[i] = (uint8_t)(v >> (8 * i)); } }
static void put_f64(uint8_t *b, double d) { uint64_t v; memcpy(&v, &d, 8); put_u64(b, v); }
static uint32_t get_u32(const uint8_t *b) { uint32_t v = 0; for (int i = 3; i >= 0; i--) { v = (v << 8) | b[i]; } return v; }
static uint64_t get_u64(const uint8_t *b) { uint64_t v = 0; for (int i = 7; i >= 0; i--) { v = (v << 8) | b[i]; } return v; }
static double get_f64(const uint8_t *b) { uint64_t v = get_u64(b); double d; memcpy(&d, &v, 8); return d; }

/* Linked with -Wl,--wrap=pthread_setschedparam (conf/modules/fdm_twinswarm.xml): Paparazzi's
 * simulated UDP and UART threads ask for SCHED_FIFO; a lockstep simulation has no deadline, and
 * a real-time thread spinning on a socket can starve the world on the same cores. */
int __real_pthread_setschedparam(pthread_t thread, int policy, const struct sched_param *param);
int __wrap_pthread_setschedparam(pthread_t thread, int policy, const struct sched_param *param);
int __wrap_pthread_setschedparam(pthread_t thread, int policy, const struct sched_param *param)
{
  const char *rt = getenv("TWINSWARM_NPS_REALTIME");
  if ((policy == SCHED_FIFO || policy == SCHED_RR) && !(rt && strcmp(rt, "1") == 0)) {
    return 0;
  }
  return __real_pthread_setschedparam(thread, policy, param);
}

static void refused(const uint8_t *got, size_t got_n);
static void read_all(uint8_t *buf, size_t len);

static void write_all(const uint8_t *buf, size_t len)
{
  while (len > 0) {
    ssize_t n = send(sock, buf, len, MSG_NOSIGNAL);
    if (n < 0) {
      if (errno == EINTR) { continue; }
      int err = errno;
      /* Stopped (SIGSTOP) between check_dropped() and this send, this aircraft may have been
       * dropped, and the world closed: its word why waits unread in the socket. */
      uint8_t magic[4];
      if (recv(sock, magic, sizeof(magic), MSG_PEEK | MSG_DONTWAIT) == (ssize_t)sizeof(magic)
          && get_u32(magic) == TWFD_MAGIC_REFUSED) {
        read_all(magic, sizeof(magic));
        refused(NULL, 0);
      }
      fprintf(stderr, "[twinswarm fdm] send failed: %s; the world is gone, stopping NPS\n", strerror(err));
      exit(0);
    }
    buf += n;
    len -= (size_t)n;
  }
}

/* at least `min` bytes, at most `max`, in as few reads as they come in; returns how many */
static size_t read_at_least(uint8_t *buf, size_t min, size_t max)
{
  size_t have = 0;
  while (have < min) {
    ssize_t n = recv(sock, buf + have, max - have, 0);
    if (n == 0 || (n < 0 && errno == ECONNRESET)) {
      if (!have_state) {
        /* an older world, or one that could not say why: it never took this aircraft */
        fprintf(stderr, "[twinswarm fdm] the world refused aircraft %d: it %s the connection before the first step "
                "(its log says why)\n", fdm_ac_id, n == 0 ? "closed" : "reset");
        exit(2);
      }
      char dl[160];
      datalink_report(dl, sizeof(dl));
      printf("[twinswarm fdm] the world %s the connection after step %llu%s; stopping NPS\n",
             n == 0 ? "closed" : "reset", (unsigned long long)twinswarm_step, dl);
      fflush(stdout);
      exit(0);
    }
    if (n < 0) {
      if (errno == EINTR) { continue; }
      fprintf(stderr, "[twinswarm fdm] recv failed: %s; stopping NPS\n", strerror(errno));
      exit(1);
    }
    have += (size_t)n;
  }
  return have;
}

static void read_all(uint8_t *buf, size_t len)
{
  read_at_least(buf, len, len);
}

/* TWINSWARM_FDM_AC_ID, if set: an aircraft id 0-255, else exit 1 saying so */
static void read_ac_id(void)
{
  const char *env = getenv("TWINSWARM_FDM_AC_ID");
  if (!env || !*env) {
    return;
  }
  char *end = NULL;
  errno = 0;
  long v = strtol(env, &end, 10);
  if (errno != 0 || *end != '\0' || v < 0 || v > 255) {
    fprintf(stderr, "[twinswarm fdm] TWINSWARM_FDM_AC_ID must be an aircraft id, 0-255, got '%s'\n", env);
    exit(1);
  }
  fdm_ac_id = (int)v;
}

static double elapsed_s(const struct timespec *t0)
{
  struct timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return (now.tv_sec - t0->tv_sec) + 1e-9 * (now.tv_nsec - t0->tv_nsec);
}

/* TWINSWARM_FDM=unix:PATH: connect to the world's Unix-domain socket, retrying while it is not
 * there yet (or not listening) for timeout_s */
static void connect_unix(const char *path, double timeout_s)
{
  struct sockaddr_un sa;
  memset(&sa, 0, sizeof(sa));
  sa.sun_family = AF_UNIX;
  size_t n = strlen(path);
  if (n == 0 || n >= sizeof(sa.sun_path)) {
    fprintf(stderr, "[twinswarm fdm] TWINSWARM_FDM=unix:PATH: the path must be 1-%zu bytes, got %zu ('%s')\n",
            sizeof(sa.sun_path) - 1, n, path);
    exit(1);
  }
  memcpy(sa.sun_path, path, n);
  struct timespec t0;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  bool said = false;
  while (true) {
    int s = socket(AF_UNIX, SOCK_STREAM, 0);
    if (s < 0) {
      fprintf(stderr, "[twinswarm fdm] cannot make a Unix socket: %s\n", strerror(errno));
      exit(1);
    }
    if (connect(s, (struct sockaddr *)&sa, sizeof(sa)) == 0) {
      sock = s;
      return;
    }
    int err = errno;
    close(s);
    struct stat st;
    if (stat(path, &st) == 0 && !S_ISSOCK(st.st_mode)) {
      fprintf(stderr, "[twinswarm fdm] TWINSWARM_FDM=unix:%s is not a socket (the world's --autopilot-listen makes "
              "it)\n", path);
      exit(1);
    }
    if (err != ENOENT && err != ECONNREFUSED && err != EAGAIN && err != EINTR) {
      fprintf(stderr, "[twinswarm fdm] cannot connect to the world at unix:%s: %s\n", path, strerror(err));
      exit(1);
    }
    if (elapsed_s(&t0) > timeout_s) {
      fprintf(stderr, "[twinswarm fdm] no world at unix:%s after %.0f s (%s), giving up\n", path, timeout_s,
              strerror(err));
      exit(1);
    }
    if (!said) {
      printf("[twinswarm fdm] waiting for the world at unix:%s ...\n", path);
      said = true;
    }
    struct timespec pause = {0, 50 * 1000 * 1000};
    nanosleep(&pause, NULL);
  }
}

static void send_hello(double dt, const char *where)
{
  uint8_t hello[TWFD_HELLO_LEN];
  memcpy(hello, "TWFD", 4);
  put_u32(hello + 4, TWFD_VERSION);
  put_u32(hello + 8, (uint32_t)fdm_ac_id);
  put_f64(hello + 12, dt);
  write_all(hello, sizeof(hello));
  printf("[twinswarm fdm] connected to the world at %s (protocol v%u, ac_id %d, dt %.6f s)\n", where, TWFD_VERSION,
         fdm_ac_id, dt);
  if (fdm_ac_id != AC_ID) {
    printf("[twinswarm fdm] TWINSWARM_FDM_AC_ID: flies aircraft %d's copter; this build's telemetry and datalink "
           "stay aircraft %d's (a speed bench, not a run with link)\n", fdm_ac_id, (int)AC_ID);
  }
  fflush(stdout);
}

static void connect_world(double dt)
{
  const char *env = getenv("TWINSWARM_FDM");
  char addr[256];
  if (env && strlen(env) >= sizeof(addr)) {
    fprintf(stderr, "[twinswarm fdm] TWINSWARM_FDM is longer than %zu bytes: '%s'\n", sizeof(addr) - 1, env);
    exit(1);
  }
  snprintf(addr, sizeof(addr), "%s", (env && *env) ? env : TWINSWARM_FDM_DEFAULT);
  read_ac_id();

  double timeout_s = 30.;
  const char *to = getenv("TWINSWARM_FDM_CONNECT_TIMEOUT_S");
  if (to && *to) { timeout_s = atof(to); }
  const char *vb = getenv("TWINSWARM_FDM_VERBOSE");
  verbose = vb && *vb && strcmp(vb, "0") != 0;

  if (strncmp(addr, "unix:", 5) == 0) {
    connect_unix(addr + 5, timeout_s);
    send_hello(dt, addr);
    return;
  }

  char *colon = strrchr(addr, ':');
  if (!colon) {
    fprintf(stderr, "[twinswarm fdm] TWINSWARM_FDM must be host:port or unix:PATH, got '%s'\n", addr);
    exit(1);
  }
  *colon = '\0';
  const char *host = addr, *port = colon + 1;
  if (host[0] == '[') { /* [::1]:7460 */
    host++;
    char *rb = strchr(addr, ']');
    if (rb) { *rb = '\0'; }
  }

  /* retrying a refused connect: the one place where waiting is timed (start-up only) */
  struct timespec t0;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  bool said = false;
  while (true) {
    struct addrinfo hints, *res = NULL;
    memset(&hints, 0, sizeof(hints));
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    int rc = getaddrinfo(host, port, &hints, &res);
    if (rc != 0) {
      fprintf(stderr, "[twinswarm fdm] cannot resolve %s:%s: %s\n", host, port, gai_strerror(rc));
      exit(1);
    }
    for (struct addrinfo *ai = res; ai; ai = ai->ai_next) {
      int s = socket(ai->ai_family, ai->ai_socktype, ai->ai_protocol);
      if (s < 0) { continue; }
      if (connect(s, ai->ai_addr, ai->ai_addrlen) == 0) {
        sock = s;
        break;
      }
      close(s);
    }
    freeaddrinfo(res);
    if (sock >= 0) { break; }
    if (elapsed_s(&t0) > timeout_s) {
      fprintf(stderr, "[twinswarm fdm] no world at %s:%s after %.0f s, giving up\n", host, port, timeout_s);
      exit(1);
    }
    if (!said) {
      printf("[twinswarm fdm] waiting for the world at %s:%s ...\n", host, port);
      said = true;
    }
    struct timespec pause = {0, 50 * 1000 * 1000};
    nanosleep(&pause, NULL);
  }
  int one = 1;
  setsockopt(sock, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
  char where[300];
  snprintf(where, sizeof(where), "%s:%s", host, port);
  send_hello(dt, where);
}

/* quaternion of a rotation matrix (Shepperd), the double counterpart of float_quat_of_rmat */
static void quat_of_rmat_d(struct DoubleQuat *q, struct DoubleRMat *r)
{
  const double tr = RMAT_TRACE(*r);
  if (tr > 0) {
    const double two_qi = sqrt(1. + tr);
    const double four_qi = 2. * two_qi;
    q->qi = 0.5 * two_qi;
    q->qx = (RMAT_ELMT(*r, 1, 2) - RMAT_ELMT(*r, 2, 1)) / four_qi;
    q->qy = (RMAT_ELMT(*r, 2, 0) - RMAT_ELMT(*r, 0, 2)) / four_qi;
    q->qz = (RMAT_ELMT(*r, 0, 1) - RMAT_ELMT(*r, 1, 0)) / four_qi;
  } else if (RMAT_ELMT(*r, 0, 0) > RMAT_ELMT(*r, 1, 1) && RMAT_ELMT(*r, 0, 0) > RMAT_ELMT(*r, 2, 2)) {
    const double two_qx = sqrt(RMAT_ELMT(*r, 0, 0) - RMAT_ELMT(*r, 1, 1) - RMAT_ELMT(*r, 2, 2) + 1);
    const double four_qx = 2. * two_qx;
    q->qi = (RMAT_ELMT(*r, 1, 2) - RMAT_ELMT(*r, 2, 1)) / four_qx;
    q->qx = 0.5 * two_qx;
    q->qy = (RMAT_ELMT(*r, 0, 1) + RMAT_ELMT(*r, 1, 0)) / four_qx;
    q->qz = (RMAT_ELMT(*r, 2, 0) + RMAT_ELMT(*r, 0, 2)) / four_qx;
  } else if (RMAT_ELMT(*r, 1, 1) > RMAT_ELMT(*r, 2, 2)) {
    const double two_qy = sqrt(RMAT_ELMT(*r, 1, 1) - RMAT_ELMT(*r, 0, 0) - RMAT_ELMT(*r, 2, 2) + 1);
    const double four_qy = 2. * two_qy;
    q->qi = (RMAT_ELMT(*r, 2, 0) - RMAT_ELMT(*r, 0, 2)) / four_qy;
    q->qx = (RMAT_ELMT(*r, 0, 1) + RMAT_ELMT(*r, 1, 0)) / four_qy;
    q->qy = 0.5 * two_qy;
    q->qz = (RMAT_ELMT(*r, 1, 2) + RMAT_ELMT(*r, 2, 1)) / four_qy;
  } else {
    const double two_qz = sqrt(RMAT_ELMT(*r, 2, 2) - RMAT_ELMT(*r, 0, 0) - RMAT_ELMT(*r, 1, 1) + 1);
    const double four_qz = 2. * two_qz;
    q->qi = (RMAT_ELMT(*r, 0, 1) - RMAT_ELMT(*r, 1, 0)) / four_qz;
    q->qx = (RMAT_ELMT(*r, 2, 0) + RMAT_ELMT(*r, 0, 2)) / four_qz;
    q->qy = (RMAT_ELMT(*r, 1, 2) + RMAT_ELMT(*r, 2, 1)) / four_qz;
    q->qz = 0.5 * two_qz;
  }
}

static void init_ltp(void)
{
  /* the INS's origin (modules/ins/ins.c): NAV_ALT0 = ground above MSL, NAV_MSL0 = geoid height */
  struct LlaCoor_d lla0;
  lla0.lat = RadOfDeg((double)NAV_LAT0 / 1e7);
  lla0.lon = RadOfDeg((double)NAV_LON0 / 1e7);
  lla0.alt = ((double)NAV_ALT0 + (double)NAV_MSL0) / 1000.;
  ltp_def_from_lla_d(&ltpdef, &lla0);
  ground_hmsl = (double)NAV_ALT0 / 1000.;
  ltpdef.hmsl = ground_hmsl;
  quat_of_rmat_d(&ecef_to_ltp_quat, &ltpdef.ltp_of_ecef);

  fdm.ecef_pos = ltpdef.ecef;
  fdm.lla_pos = ltpdef.lla;

  fdm.ltp_g.x = 0.;
  fdm.ltp_g.y = 0.;
  fdm.ltp_g.z = 9.81;

#ifdef AHRS_H_X
  fdm.ltp_h.x = AHRS_H_X;
  fdm.ltp_h.y = AHRS_H_Y;
  fdm.ltp_h.z = AHRS_H_Z;
  PRINT_CONFIG_MSG("Using magnetic field as defined in airframe file.")
#else
  fdm.ltp_h.x = 0.4912;
  fdm.ltp_h.y = 0.1225;
  fdm.ltp_h.z = 0.8624;
#endif
}

/* after the refused record's magic (and `got` bytes of the rest, read with it): print why and exit 2 */
static void refused(const uint8_t *got, size_t got_n)
{
  uint8_t rec[2 + 1024];
  if (got_n > sizeof(rec)) { got_n = sizeof(rec); }
  if (got_n > 0) { memcpy(rec, got, got_n); }
  if (got_n < 2) {
    read_all(rec + got_n, 2 - got_n);
    got_n = 2;
  }
  size_t len = (size_t)rec[0] | ((size_t)rec[1] << 8);
  if (len > sizeof(rec) - 3) { len = sizeof(rec) - 3; }
  if (got_n < 2 + len) {
    read_all(rec + got_n, 2 + len - got_n);
  }
  char why[1024];
  memcpy(why, rec + 2, len);
  why[len] = '\0';
  fprintf(stderr, "[twinswarm fdm] the world refused aircraft %d at step %llu: %s\n", fdm_ac_id,
          (unsigned long long)next_step, why);
  exit(2);
}

/* In lockstep nothing is pending before a step is sent, unless the world dropped this aircraft
 * (it stalled: stopped with SIGSTOP, say) and said why: read that before sending into a
 * connection the world may have closed. One non-blocking peek per step. */
static void check_dropped(void)
{
  uint8_t b[4];
  ssize_t n = recv(sock, b, sizeof(b), MSG_PEEK | MSG_DONTWAIT);
  if (n >= 0) {
    uint8_t magic[4];
    read_all(magic, 4); /* the end of the stream exits in read_all */
    if (get_u32(magic) == TWFD_MAGIC_REFUSED) {
      refused(NULL, 0);
    }
    fprintf(stderr, "[twinswarm fdm] unexpected record 0x%08x before step %llu\n", get_u32(magic),
            (unsigned long long)next_step);
    exit(1);
  }
}

/* send one step's commands, receive the state after it, fill NpsFdm */
static void exchange(bool launch, double *commands, int commands_nb)
{
  check_dropped();
  uint8_t out[TWFD_STEP_LEN];
  put_u32(out, TWFD_MAGIC_STEP);
  put_u64(out + 4, next_step);
  out[12] = launch ? 1 : 0;
  out[13] = TWFD_N_MOTORS;
  for (int i = 0; i < TWFD_N_MOTORS; i++) {
    put_f64(out + 14 + 8 * i, (commands && i < commands_nb) ? commands[i] : 0.);
  }
  write_all(out, sizeof(out));

  /* Wait for the state in poll(), not in recv(): a task asleep in a Unix socket's recv() is woken
   * (for nothing) when the world reads the commands just sent, which frees their buffer space
   * (unix_write_space wakes every sleeper on the socket); poll() sleeps for POLLIN only, so
   * the world's read costs no wake-up and only its state wakes this process. Then one read for
   * the whole record as a rule (the world writes it at once). */
  struct pollfd pfd = {sock, POLLIN, 0};
  while (poll(&pfd, 1, -1) < 0 && errno == EINTR) {}
  uint8_t in[TWFD_STATE_LEN];
  size_t have = read_at_least(in, 4, sizeof(in));
  if (get_u32(in) == TWFD_MAGIC_REFUSED) {
    refused(in + 4, have - 4);
  }
  if (have < sizeof(in)) {
    read_all(in + have, sizeof(in) - have);
  }
  uint32_t magic = get_u32(in);
  uint64_t step = get_u64(in + 4);
  if (magic != TWFD_MAGIC_STATE || step != next_step) {
    fprintf(stderr, "[twinswarm fdm] bad state record: magic 0x%08x (want 0x%08x), step %llu (want %llu)\n",
            magic, TWFD_MAGIC_STATE, (unsigned long long)step, (unsigned long long)next_step);
    exit(1);
  }
  double f[TWFD_STATE_NF];
  for (int i = 0; i < TWFD_STATE_NF; i++) {
    f[i] = get_f64(in + 12 + 8 * i);
  }
  uint8_t crashed = in[12 + 8 * TWFD_STATE_NF];
  uplinks_named = get_u32(in + 12 + 8 * TWFD_STATE_NF + 1);
  have_state = true;
  twinswarm_step = next_step;
  next_step++;

  const double *t_s = f, *pos = f + 1, *vel = f + 4, *acc = f + 7, *quat = f + 10, *rates = f + 14,
                *body_acc = f + 17, *agl = f + 20, *sonar = f + 21, *ir = f + 25;

  twinswarm_time_s = *t_s;
  for (int i = 0; i < 4; i++) {
    twinswarm_sonar_m[i] = (float)sonar[i];
  }
  twinswarm_ir_m = (float)*ir;
  if (crashed && !twinswarm_crashed) {
    printf("[twinswarm fdm] the world reports a crash at t = %.3f s (step %llu)\n", *t_s,
           (unsigned long long)twinswarm_step);
    fflush(stdout);
  }
  twinswarm_crashed = crashed;

  fdm.time = *t_s;
  fdm.curr_dt = fdm.init_dt;

  /* position: LTP (NED) = the world's arena frame */
  struct NedCoor_d ned_pos = {pos[0], pos[1], pos[2]};
  fdm.ltpprz_pos = ned_pos;
  ecef_of_ned_point_d(&fdm.ecef_pos, &ltpdef, &ned_pos);
  lla_of_ecef_d(&fdm.lla_pos, &fdm.ecef_pos);
  fdm.lla_pos_pprz = fdm.lla_pos;
  fdm.lla_pos_geod = fdm.lla_pos;
  fdm.lla_pos_geoc = fdm.lla_pos;
  fdm.hmsl = ground_hmsl - ned_pos.z;
  fdm.agl = *agl;
  fdm.on_ground = fdm.agl < 0.01;

  /* attitude */
  struct DoubleQuat q = {quat[0], quat[1], quat[2], quat[3]};
  double qn = sqrt(q.qi * q.qi + q.qx * q.qx + q.qy * q.qy + q.qz * q.qz);
  if (qn > 1e-9) {
    q.qi /= qn; q.qx /= qn; q.qy /= qn; q.qz /= qn;
  } else {
    q.qi = 1.; q.qx = 0.; q.qy = 0.; q.qz = 0.;
  }
  fdm.ltp_to_body_quat = q;
  double_eulers_of_quat(&fdm.ltp_to_body_eulers, &fdm.ltp_to_body_quat);
  fdm.ltpprz_to_body_quat = fdm.ltp_to_body_quat;
  fdm.ltpprz_to_body_eulers = fdm.ltp_to_body_eulers;
  double_quat_comp(&fdm.ecef_to_body_quat, &ecef_to_ltp_quat, &fdm.ltp_to_body_quat);

  /* velocities, wrt the (non-rotating, here) earth */
  struct NedCoor_d ned_vel = {vel[0], vel[1], vel[2]};
  fdm.ltp_ecef_vel = ned_vel;
  fdm.ltpprz_ecef_vel = ned_vel;
  ecef_of_ned_vect_d(&fdm.ecef_ecef_vel, &ltpdef, &ned_vel);
  struct DoubleVect3 v_ltp = {vel[0], vel[1], vel[2]};
  double_quat_vmult(&fdm.body_ecef_vel, &fdm.ltp_to_body_quat, &v_ltp);

  /* accelerations: kinematic (without gravity) ... */
  struct NedCoor_d ned_acc = {acc[0], acc[1], acc[2]};
  fdm.ltp_ecef_accel = ned_acc;
  fdm.ltpprz_ecef_accel = ned_acc;
  ecef_of_ned_vect_d(&fdm.ecef_ecef_accel, &ltpdef, &ned_acc);
  struct DoubleVect3 a_ltp = {acc[0], acc[1], acc[2]};
  double_quat_vmult(&fdm.body_ecef_accel, &fdm.ltp_to_body_quat, &a_ltp);
  fdm.body_inertial_accel = fdm.body_ecef_accel; /* earth rotation neglected, as in the world */
  /* ... and as an accelerometer reads it (specific force, incl. the reaction to gravity) */
  fdm.body_accel.x = body_acc[0];
  fdm.body_accel.y = body_acc[1];
  fdm.body_accel.z = body_acc[2];

  /* body rates; angular acceleration by finite difference */
  struct DoubleRates r = {rates[0], rates[1], rates[2]};
  if (have_last_rates && fdm.init_dt > 0) {
    fdm.body_ecef_rotaccel.p = (r.p - last_rates.p) / fdm.init_dt;
    fdm.body_ecef_rotaccel.q = (r.q - last_rates.q) / fdm.init_dt;
    fdm.body_ecef_rotaccel.r = (r.r - last_rates.r) / fdm.init_dt;
  } else {
    fdm.body_ecef_rotaccel.p = fdm.body_ecef_rotaccel.q = fdm.body_ecef_rotaccel.r = 0.;
  }
  last_rates = r;
  have_last_rates = true;
  fdm.body_ecef_rotvel = r;
  fdm.body_inertial_rotvel = r;
  fdm.body_inertial_rotaccel = fdm.body_ecef_rotaccel;

  /* air: indoor, ISA pressure at the copter's height, still air unless NPS sets wind */
  struct DoubleVect3 air = {vel[0] - fdm.wind.x, vel[1] - fdm.wind.y, vel[2] - fdm.wind.z};
  fdm.airspeed = sqrt(air.x * air.x + air.y * air.y + air.z * air.z);
  fdm.pressure = pprz_isa_pressure_of_altitude((float)fdm.hmsl);
  fdm.pressure_sl = PPRZ_ISA_SEA_LEVEL_PRESSURE;
  fdm.dynamic_pressure = 0.5 * PPRZ_ISA_AIR_DENSITY * fdm.airspeed * fdm.airspeed;
  fdm.total_pressure = fdm.pressure + fdm.dynamic_pressure;
  fdm.temperature = temperature_c;
  fdm.aoa = 0.;
  fdm.sideslip = 0.;

  /* counted: take what the datalink's device holds now, every step (its own buffer is small) */
  if (uplinks_named != TWFD_UPLINKS_NOT_COUNTED) {
    datalink_drain();
  }

  if (verbose && (twinswarm_step % 1000 == 0)) {
    printf("[twinswarm fdm] step %llu t %.3f pos %.3f %.3f %.3f cmd %.3f %.3f %.3f %.3f\n",
           (unsigned long long)twinswarm_step, *t_s, pos[0], pos[1], pos[2],
           commands ? commands[0] : 0., commands ? commands[1] : 0.,
           commands ? commands[2] : 0., commands ? commands[3] : 0.);
  }
}

void nps_fdm_init(double dt)
{
  memset(&fdm, 0, sizeof(fdm));
  fdm.init_dt = dt;
  fdm.curr_dt = dt;
  fdm.time = 0.;
  fdm.on_ground = TRUE;
  fdm.nan_count = 0;
  fdm.pressure = -1;
  fdm.pressure_sl = PPRZ_ISA_SEA_LEVEL_PRESSURE;
  fdm.total_pressure = -1;
  fdm.dynamic_pressure = -1;
  fdm.temperature = -1;
  fdm.num_engines = TWFD_N_MOTORS;

  init_ltp();
  connect_world(dt);

  /* step 0: fill every field before the sensors initialise */
  double zero[TWFD_N_MOTORS] = {0., 0., 0., 0.};
  exchange(false, zero, TWFD_N_MOTORS);
}

void nps_fdm_run_step(bool launch, double *commands, int commands_nb)
{
  exchange(launch, commands, commands_nb);
}

void nps_fdm_set_wind(double speed, double dir)
{
  /* dir: direction the wind comes from, rad from north, as for the other FDMs */
  fdm.wind.x = -speed * cos(dir);
  fdm.wind.y = -speed * sin(dir);
  fdm.wind.z = 0.;
}

void nps_fdm_set_wind_ned(double wind_north, double wind_east, double wind_down)
{
  fdm.wind.x = wind_north;
  fdm.wind.y = wind_east;
  fdm.wind.z = wind_down;
}

void nps_fdm_set_turbulence(double wind_speed __attribute__((unused)),
                            int turbulence_severity __attribute__((unused)))
{
}

void nps_fdm_set_temperature(double temp, double h __attribute__((unused)))
{
  temperature_c = temp;
}

/*
 * The uplink in the lockstep (see the top of this file). TWINSWARM_FDM_UPLINK is defined for
 * the nps target, which links -Wl,--wrap=pprz_check_and_parse (conf/modules/fdm_twinswarm.xml).
 * Everything here runs in NPS's main-loop thread (the flight model's step and the autopilot's
 * datalink events); the device is filled by Paparazzi's UDP thread under its own lock.
 */
#if TWINSWARM_FDM_UPLINK

#include "pprzlink/pprz_transport.h"
#include "pprzlink/dl_protocol.h"

#define DL_QUEUE_LEN 128

struct dl_frame {
  uint8_t len;
  bool counted;                       /* an uplink message the world counts */
  uint8_t payload[TRANSPORT_PAYLOAD_LEN];
};

void __real_pprz_check_and_parse(struct link_device *dev, struct pprz_transport *trans, uint8_t *buf,
                                 bool *msg_available);
void __wrap_pprz_check_and_parse(struct link_device *dev, struct pprz_transport *trans, uint8_t *buf,
                                 bool *msg_available);

static struct link_device *dl_dev = NULL;    /* the datalink's device and transport (the first seen) */
static struct pprz_transport *dl_trans = NULL;
static struct dl_frame dl_queue[DL_QUEUE_LEN]; /* in arrival order */
static int dl_queued = 0;
static uint64_t uplinks_received = 0;        /* counted messages taken from the device */
static uint64_t uplinks_given = 0;           /* counted messages given to the autopilot */
static uint64_t others_given = 0;            /* the rest (link's PING, a GCS's messages) */
static double uplink_wait_s = 0.;            /* wall time the autopilot waited for counted ones */
static double uplink_timeout_s = -1.;

/* An uplink message for this aircraft, the kind the world counts: SONAR_UPLINK or VIRTUAL_SONAR
 * (whichever this aircraft's messages define), its ac_id field this aircraft's. */
static bool dl_counted(uint8_t *p, uint8_t len)
{
  if (len < 5 || pprzlink_get_msg_class_id(p) != DL_datalink_CLASS_ID) {
    return false;
  }
  uint8_t id __attribute__((unused)) = pprzlink_get_msg_id(p);
#ifdef DL_SONAR_UPLINK
  if (id == DL_SONAR_UPLINK && DL_SONAR_UPLINK_ac_id(p) == AC_ID) {
    return true;
  }
#endif
#ifdef DL_VIRTUAL_SONAR
  if (id == DL_VIRTUAL_SONAR && DL_VIRTUAL_SONAR_ac_id(p) == AC_ID) {
    return true;
  }
#endif
  return false;
}

/* every complete frame the device holds, through pprzlink's own parser, into the queue */
static void datalink_drain(void)
{
  if (dl_dev == NULL) {
    return;
  }
  static uint8_t scratch[TRANSPORT_PAYLOAD_LEN];
  while (dl_dev->char_available(dl_dev->periph)) {
    bool got = false;
    __real_pprz_check_and_parse(dl_dev, dl_trans, scratch, &got);
    if (!got) {
      continue; /* a partial frame or noise: the parser took the bytes */
    }
    if (dl_queued == DL_QUEUE_LEN) {
      fprintf(stderr, "[twinswarm fdm] aircraft %d: %d datalink messages waiting for the autopilot at step %llu "
              "(the world named %u uplinks, %llu received): stopping NPS\n", (int)AC_ID, DL_QUEUE_LEN,
              (unsigned long long)twinswarm_step, uplinks_named, (unsigned long long)uplinks_received);
      exit(3);
    }
    struct dl_frame *f = &dl_queue[dl_queued++];
    f->len = dl_trans->trans_rx.payload_len;
    memcpy(f->payload, scratch, f->len);
    f->counted = dl_counted(f->payload, f->len);
    if (f->counted) {
      uplinks_received++;
    }
  }
}

static double now_s(void)
{
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

/* Until the datalink has received the counted messages the last state named. The wall clock
 * bounds the wait only: what the autopilot is given does not depend on it. */
static void datalink_wait_for_named(void)
{
  if (uplink_timeout_s < 0) {
    const char *to = getenv("TWINSWARM_FDM_UPLINK_TIMEOUT_S");
    uplink_timeout_s = (to && *to) ? atof(to) : 5.;
  }
  datalink_drain();
  if (uplinks_received >= uplinks_named) {
    return;
  }
  double t0 = now_s();
  while (uplinks_received < uplinks_named) {
    if (now_s() - t0 > uplink_timeout_s) {
      fprintf(stderr, "[twinswarm fdm] aircraft %d, step %llu: the world sent %u uplink messages to it through "
              "Paparazzi's link, its datalink received %llu within %.1f s: one was lost on the way (is link "
              "running with -udp and this aircraft's ports, and does this aircraft's messages.xml define the "
              "uplink the world sends, SONAR_UPLINK or VIRTUAL_SONAR? TWINSWARM_FDM_UPLINK_TIMEOUT_S sets the "
              "wait); stopping NPS\n", (int)AC_ID,
              (unsigned long long)twinswarm_step, uplinks_named, (unsigned long long)uplinks_received,
              uplink_timeout_s);
      exit(3);
    }
    struct timespec pause = {0, 20 * 1000};
    nanosleep(&pause, NULL);
    datalink_drain();
  }
  uplink_wait_s += now_s() - t0;
}

/* Linked with -Wl,--wrap=pprz_check_and_parse: Paparazzi's datalink event (pprz_dl_event) asks
 * for the next message here. Counted messages up to the named count first, in order; then the
 * others; a counted message beyond the count stays queued. */
void __wrap_pprz_check_and_parse(struct link_device *dev, struct pprz_transport *trans, uint8_t *buf,
                                 bool *msg_available)
{
  if (dl_dev == NULL) {
    dl_dev = dev;
    dl_trans = trans;
  }
  if (dev != dl_dev || trans != dl_trans) {
    __real_pprz_check_and_parse(dev, trans, buf, msg_available); /* another device: not ours */
    return;
  }
  bool counting = uplinks_named != TWFD_UPLINKS_NOT_COUNTED;
  if (!counting && dl_queued == 0) {
    __real_pprz_check_and_parse(dev, trans, buf, msg_available); /* Paparazzi's own datalink */
    return;
  }
  if (counting) {
    datalink_wait_for_named();
  } else {
    datalink_drain();
  }
  int pick = counting ? -1 : 0; /* not counted (any more): what is left, in arrival order */
  for (int k = 0; counting && k < dl_queued; k++) {
    if (dl_queue[k].counted) {
      if (uplinks_given < uplinks_named) {
        pick = k;
      }
      break; /* counted messages go in order: the first one decides */
    }
  }
  if (pick < 0) {
    for (int k = 0; k < dl_queued; k++) {
      if (!dl_queue[k].counted) {
        pick = k;
        break;
      }
    }
  }
  if (pick < 0 || pick >= dl_queued) {
    return;
  }
  struct dl_frame *f = &dl_queue[pick];
  memcpy(buf, f->payload, f->len);
  *msg_available = true;
  if (f->counted) {
    uplinks_given++;
  } else {
    others_given++;
  }
  memmove(&dl_queue[pick], &dl_queue[pick + 1], (size_t)(dl_queued - pick - 1) * sizeof(dl_queue[0]));
  dl_queued--;
}

static void datalink_report(char *buf, size_t len)
{
  if (uplinks_named == TWFD_UPLINKS_NOT_COUNTED && uplinks_given == 0) {
    snprintf(buf, len, " (uplink not counted by the world)");
    return;
  }
  snprintf(buf, len, " (uplink in the lockstep: %u named, %llu given to the autopilot, waited %.3f s for them; "
           "%llu other datalink messages)", uplinks_named == TWFD_UPLINKS_NOT_COUNTED ? 0u : uplinks_named,
           (unsigned long long)uplinks_given, uplink_wait_s, (unsigned long long)others_given);
}

#else /* !TWINSWARM_FDM_UPLINK: HITL, no autopilot datalink in this process */

static void datalink_drain(void) {}
static void datalink_report(char *buf, size_t len) { if (len > 0) { buf[0] = '\0'; } }

#endif
