#!/usr/bin/env python3
"""A stand-in Twinswarm world for bringing up Paparazzi NPS with the Twinswarm FDM.

Speaks protocol v2 (and v1) of paparazzi/sw/nps_fdm_twinswarm.c as the server (it counts no
uplink), over TCP on loopback, in lockstep (each NPS step is answered at once; no wall clock), and
integrates a plain rigid-body quadrotor: mass 0.4 kg, X-frame with a 0.2 m motor diagonal, thrust
per motor k*cmd^2 (3 N at full command), yaw torque d*T per motor, first-order motor lag, linear
drag, gravity, a floor at z = 0 and the walls of a rectangular arena (--arena 6 or 4x3: x "north"
by y "east", m), which the four sonars see as horizontal rays along the body axes (front, right,
back, left; NaN beyond --sonar-range) and which end the flight as a crash when the copter's centre
reaches one. The summary reports the closest the copter's centre came to a wall. It is a bring-up
tool, not Twinswarm's model.

Motor order is the FINken airframe's (twinswarm_finken.xml): 0 front right (CW seen from above),
1 back right (CCW), 2 back left (CW), 3 front left (CCW).

    python3 paparazzi/fake_world.py --port 7460 --duration 30 --csv /tmp/hover.csv

Stdlib only. After --duration simulated seconds it closes the connection, which ends NPS, and
prints a summary (height reached, hold error, real-time factor) as text and, with --json, JSON.
"""

import argparse
import json
import math
import socket
import struct
import sys
import time

HELLO = struct.Struct("<4sIId")                 # 20 B
STEP = struct.Struct("<IQBB4d")                 # 46 B
STATE = struct.Struct("<IQ" + "d" * 26 + "B")   # 221 B (v1; v2 appends u32 uplinks)
UPLINKS_NOT_COUNTED = struct.pack("<I", 0xFFFFFFFF)  # v2: this world counts no uplink
MAGIC_STEP = 0x54575331
MAGIC_STATE = 0x54575332
G = 9.81


def recv_exact(conn, n):
    buf = bytearray()
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


# quaternion helpers: q = (w, x, y, z), ned_to_body, Hamilton product; v_ned = R(q) v_body
def qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def rmat(q):
    """body -> ned rotation matrix (rows)"""
    w, x, y, z = q
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))


def eulers(q):
    w, x, y, z = q
    phi = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    theta = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    psi = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return phi, theta, psi


class Quad:
    def __init__(self, a):
        self.m = a.mass
        self.k = a.max_thrust          # T = k cmd^2, N
        self.d = a.yaw_ratio           # yaw torque / thrust, m
        self.tau = a.motor_lag
        self.drag = a.drag
        arm = a.diagonal / 2.0 / math.sqrt(2.0)
        # (x forward, y right) of each motor, and +1 for CCW (reaction torque +z-down)
        # Spin as Twinswarm's FINken (the airframe's YAW_COEF is mirrored from fink3.xml for it):
        # front right and back left counter-clockwise seen from above.
        self.motors = ((arm, arm, +1), (-arm, arm, -1), (-arm, -arm, +1), (arm, -arm, -1))
        mb, mm = a.mass - 4 * 0.025, 0.025      # body box + 4 motor point masses
        self.I = (mb * (0.1 ** 2 + 0.04 ** 2) / 12 + 4 * mm * arm * arm,
                  mb * (0.1 ** 2 + 0.04 ** 2) / 12 + 4 * mm * arm * arm,
                  mb * (0.1 ** 2 + 0.1 ** 2) / 12 + 4 * mm * 2 * arm * arm)
        self.half = (a.arena[0] / 2.0, a.arena[1] / 2.0)
        self.sonar_range = a.sonar_range
        self.pos = [a.x, a.y, 0.0]
        self.vel = [0.0, 0.0, 0.0]
        self.acc = [0.0, 0.0, 0.0]
        self.q = (math.cos(a.yaw / 2), 0.0, 0.0, math.sin(a.yaw / 2))
        self.w = [0.0, 0.0, 0.0]
        self.thrust = [0.0] * 4
        self.t = 0.0
        self.crashed = False
        # rotor tolerance: motor i gives (1 + imbalance[i]) of its nominal thrust
        self.gain = [1.0 + e for e in a.imbalance]
        self.kick_at = a.kick_at
        self.kick = a.kick

    def step(self, cmds, dt):
        # motors: first-order lag on the thrust command
        alpha = 1.0 if self.tau <= 0 else min(1.0, dt / self.tau)
        for i in range(4):
            c = min(1.0, max(0.0, cmds[i]))
            self.thrust[i] += alpha * (self.k * self.gain[i] * c * c - self.thrust[i])
        if self.kick_at is not None and self.t <= self.kick_at < self.t + dt and self.pos[2] < -0.05:
            # a gust: sudden body rates (roll, pitch, yaw)
            self.w = [self.w[0] + self.kick[0], self.w[1] + self.kick[1], self.w[2] + self.kick[2]]
            print(f"fake world: kick {self.kick} rad/s at t = {self.t:.3f} s", file=sys.stderr)
        T = sum(self.thrust)
        tx = ty = tz = 0.0
        for (mx, my, spin), Ti in zip(self.motors, self.thrust):
            tx += -my * Ti
            ty += mx * Ti
            tz += spin * self.d * Ti
        R = rmat(self.q)
        # translational: thrust along -z body, gravity, linear drag
        ax = (R[0][2] * -T) / self.m - self.drag * self.vel[0]
        ay = (R[1][2] * -T) / self.m - self.drag * self.vel[1]
        az = (R[2][2] * -T) / self.m + G - self.drag * self.vel[2]
        # rotational: Euler's equations
        Ix, Iy, Iz = self.I
        p, q, r = self.w
        dp = (tx - (Iz - Iy) * q * r) / Ix
        dq = (ty - (Ix - Iz) * r * p) / Iy
        dr = (tz - (Iy - Ix) * p * q) / Iz
        if self.crashed:
            ax = ay = 0.0
            az = G
            dp = dq = dr = 0.0
            self.w = [0.0, 0.0, 0.0]
        v0 = list(self.vel)
        # semi-implicit Euler
        self.vel[0] += ax * dt
        self.vel[1] += ay * dt
        self.vel[2] += az * dt
        self.w[0] += dp * dt
        self.w[1] += dq * dt
        self.w[2] += dr * dt
        for i in range(3):
            self.pos[i] += self.vel[i] * dt
        # floor at z = 0 (NED: z > 0 is below it)
        if self.pos[2] >= 0.0:
            if self.vel[2] > 0.6 and not self.crashed:
                print(f"fake world: hard landing at {self.vel[2]:.2f} m/s, t = {self.t:.3f} s", file=sys.stderr)
            self.pos[2] = 0.0
            if self.vel[2] > 0.0:
                self.vel[2] = 0.0
            if T < self.m * G or self.crashed:
                # resting: friction stops it, it sits level with its heading
                self.vel[0] = self.vel[1] = 0.0
                phi, theta, psi = eulers(self.q)
                self.q = (math.cos(psi / 2), 0.0, 0.0, math.sin(psi / 2))
                self.w = [0.0, 0.0, 0.0]
        # attitude
        p, q, r = self.w
        dq_ = qmul(self.q, (0.0, p, q, r))
        qq = tuple(self.q[i] + 0.5 * dt * dq_[i] for i in range(4))
        n = math.sqrt(sum(c * c for c in qq))
        self.q = tuple(c / n for c in qq)
        self.acc = [(self.vel[i] - v0[i]) / dt for i in range(3)]
        self.t += dt
        phi, theta, _ = eulers(self.q)
        if not self.crashed and math.cos(phi) * math.cos(theta) < 0.5:
            self.crashed = True
            print(f"fake world: crash (tilt > 60 deg) at t = {self.t:.3f} s", file=sys.stderr)
        for i in (0, 1):
            if abs(self.pos[i]) > self.half[i]:
                self.pos[i] = math.copysign(self.half[i], self.pos[i])
                self.vel[i] = 0.0
                if not self.crashed:
                    self.crashed = True
                    print(f"fake world: crash (wall) at t = {self.t:.3f} s", file=sys.stderr)

    def sensors(self):
        R = rmat(self.q)
        # specific force in body axes: R^T (a - g)
        f = (self.acc[0], self.acc[1], self.acc[2] - G)
        body_acc = tuple(R[0][j] * f[0] + R[1][j] * f[1] + R[2][j] * f[2] for j in range(3))
        agl = -self.pos[2]
        phi, theta, psi = eulers(self.q)
        tilt = math.cos(phi) * math.cos(theta)
        ir = agl / tilt if tilt > 0.1 and agl / tilt <= 1.5 else float("nan")
        sonar = []
        for k in range(4):      # front, right, back, left: horizontal rays to the walls
            ang = psi + k * math.pi / 2
            dx, dy = math.cos(ang), math.sin(ang)
            best = float("inf")
            for comp, dcomp, half in ((self.pos[0], dx, self.half[0]), (self.pos[1], dy, self.half[1])):
                if abs(dcomp) > 1e-9:
                    wall = half if dcomp > 0 else -half
                    best = min(best, (wall - comp) / dcomp)
            sonar.append(best if best <= self.sonar_range else float("nan"))
        return body_acc, agl, sonar, ir


def arena_size(text):
    parts = text.lower().split("x")
    if len(parts) == 1:
        return (float(parts[0]), float(parts[0]))
    if len(parts) == 2:
        return (float(parts[0]), float(parts[1]))
    raise argparse.ArgumentTypeError(f"arena size: 6 or 4x3, not {text!r}")


def wall_distance(quad):
    """distance of the copter's centre to the nearest wall, m"""
    return min(quad.half[0] - abs(quad.pos[0]), quad.half[1] - abs(quad.pos[1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=7460)
    ap.add_argument("--duration", type=float, default=30.0, help="simulated seconds, then close")
    ap.add_argument("--mass", type=float, default=0.4)
    ap.add_argument("--diagonal", type=float, default=0.2)
    ap.add_argument("--max-thrust", type=float, default=3.0, help="N per motor at command 1")
    ap.add_argument("--yaw-ratio", type=float, default=0.0165, help="yaw torque / thrust, m")
    ap.add_argument("--motor-lag", type=float, default=0.015, help="s")
    ap.add_argument("--drag", type=float, default=0.3, help="linear drag, 1/s")
    ap.add_argument("--arena", type=arena_size, default=(6.0, 6.0),
                    help="arena size, m: a square's side (6) or x by y (4x3: 4 m north, 3 m east)")
    ap.add_argument("--sonar-range", type=float, default=7.65, help="sonars see no wall beyond this, m")
    ap.add_argument("--radius", type=float, default=0.15,
                    help="the copter touches a wall when its centre comes closer than this, m")
    ap.add_argument("--x", type=float, default=0.0)
    ap.add_argument("--y", type=float, default=0.0)
    ap.add_argument("--yaw", type=float, default=0.0, help="initial heading, rad")
    ap.add_argument("--imbalance", type=float, nargs=4, default=[0.0] * 4, metavar="E",
                    help="relative thrust error of motors 0..3, e.g. -0.03 0 0 0")
    ap.add_argument("--kick-at", type=float, help="simulated time of a rate kick (only in the air)")
    ap.add_argument("--kick", type=float, nargs=3, default=[1.0, -1.0, 0.5], metavar="W",
                    help="the kick's body rates p q r, rad/s")
    ap.add_argument("--target", type=float, default=1.0, help="height the flight plan holds, m")
    ap.add_argument("--pace", type=float, default=0.0,
                    help="at most this many simulated seconds per wall second (0: as fast as possible; "
                         "1: real time, e.g. to send datalink at wall-clock rates)")
    ap.add_argument("--csv", help="write the state every 10 ms here")
    ap.add_argument("--json", help="write the summary here")
    a = ap.parse_args()

    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((a.host, a.port))
    srv.listen(1)
    print(f"fake world: listening on {a.host}:{a.port}", flush=True)
    conn, peer = srv.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    hello = recv_exact(conn, HELLO.size)
    magic, version, ac_id, dt = HELLO.unpack(hello)
    if magic != b"TWFD" or version not in (1, 2):
        sys.exit(f"fake world: bad hello {hello!r}")
    print(f"fake world: NPS ac_id {ac_id} connected from {peer}, dt {dt:.6f} s ({1 / dt:.1f} steps/s)", flush=True)

    quad = Quad(a)
    csv = open(a.csv, "w") if a.csv else None
    if csv:
        csv.write("t,x,y,z,height,vz,phi_deg,theta_deg,psi_deg,c0,c1,c2,c3,crashed\n")
    every = max(1, round(0.01 / dt))
    steps = 0
    t_wall0 = time.perf_counter()
    heights = []              # (t, height) every 10 ms
    first_cmd_t = None
    last_cmds = (0.0,) * 4
    max_cmd = 0.0
    max_tilt = final_tilt = 0.0
    # walls: over the flight (from the first time above 0.5 m)
    airborne_t = None
    min_wall = None           # (distance, t, x, y)
    approaches = 0            # entries into 1.0 m of a wall, after having been 1.4 m away from it
    near = [False] * 4        # per wall: +x, -x, +y, -y
    path = 0.0
    max_speed = 0.0
    last_xy = None
    x_span = [math.inf, -math.inf]
    y_span = [math.inf, -math.inf]
    while quad.t < a.duration:
        raw = recv_exact(conn, STEP.size)
        if raw is None:
            print("fake world: NPS closed the connection", flush=True)
            break
        magic, step, launch, n, c0, c1, c2, c3 = STEP.unpack(raw)
        if magic != MAGIC_STEP or n != 4:
            sys.exit(f"fake world: bad step record (magic {magic:#x}, n {n})")
        cmds = (c0, c1, c2, c3)
        last_cmds = cmds
        if first_cmd_t is None and max(cmds) > 0.0:
            first_cmd_t = quad.t
        max_cmd = max(max_cmd, max(cmds))
        quad.step(cmds, dt)
        body_acc, agl, sonar, ir = quad.sensors()
        out = STATE.pack(MAGIC_STATE, step, quad.t, *quad.pos, *quad.vel, *quad.acc, *quad.q,
                         *quad.w, *body_acc, agl, *sonar, ir, 1 if quad.crashed else 0)
        if version == 2:
            out += UPLINKS_NOT_COUNTED
        conn.sendall(out)
        steps += 1
        if steps % every == 0:
            if a.pace > 0:
                ahead = quad.t / a.pace - (time.perf_counter() - t_wall0)
                if ahead > 0:
                    time.sleep(ahead)
            if airborne_t is None and -quad.pos[2] > 0.5:
                airborne_t = quad.t
            if airborne_t is not None:
                d = wall_distance(quad)
                if min_wall is None or d < min_wall[0]:
                    min_wall = (d, quad.t, quad.pos[0], quad.pos[1])
                for w, dw in enumerate((quad.half[0] - quad.pos[0], quad.half[0] + quad.pos[0],
                                        quad.half[1] - quad.pos[1], quad.half[1] + quad.pos[1])):
                    if not near[w] and dw < 1.0:
                        near[w] = True
                        approaches += 1
                    elif near[w] and dw > 1.4:
                        near[w] = False
                if last_xy is not None:
                    path += math.hypot(quad.pos[0] - last_xy[0], quad.pos[1] - last_xy[1])
                last_xy = (quad.pos[0], quad.pos[1])
                max_speed = max(max_speed, math.hypot(quad.vel[0], quad.vel[1]))
                x_span = [min(x_span[0], quad.pos[0]), max(x_span[1], quad.pos[0])]
                y_span = [min(y_span[0], quad.pos[1]), max(y_span[1], quad.pos[1])]
            heights.append((quad.t, -quad.pos[2]))
            phi, theta, _ = eulers(quad.q)
            final_tilt = math.degrees(math.acos(max(-1.0, min(1.0, math.cos(phi) * math.cos(theta)))))
            max_tilt = max(max_tilt, final_tilt)
            if csv:
                phi, theta, psi = eulers(quad.q)
                csv.write(f"{quad.t:.4f},{quad.pos[0]:.4f},{quad.pos[1]:.4f},{quad.pos[2]:.4f},{-quad.pos[2]:.4f},"
                          f"{quad.vel[2]:.4f},{math.degrees(phi):.3f},{math.degrees(theta):.3f},"
                          f"{math.degrees(psi):.3f},{c0:.4f},{c1:.4f},{c2:.4f},{c3:.4f},{int(quad.crashed)}\n")
    wall = time.perf_counter() - t_wall0
    # close cleanly: no more answers; NPS reads EOF and exits, then we see its EOF
    try:
        conn.shutdown(socket.SHUT_WR)
        conn.settimeout(10.0)
        while conn.recv(4096):
            pass
    except OSError:
        pass
    conn.close()
    srv.close()
    if csv:
        csv.close()

    # summary: take-off, climb, hold
    summ = {"steps": steps, "sim_s": round(quad.t, 4), "wall_s": round(wall, 3),
            "realtime_factor": round(quad.t / wall, 2) if wall > 0 else None,
            "steps_per_wall_s": round(steps / wall) if wall > 0 else None,
            "dt": dt, "crashed": quad.crashed, "first_cmd_above_0_s": first_cmd_t,
            "max_cmd": round(max_cmd, 4), "last_cmds": [round(c, 4) for c in last_cmds]}
    if heights:
        hmax = max(h for _, h in heights)
        summ["max_height_m"] = round(hmax, 4)
        t_reach = next((t for t, h in heights if h >= 0.9 * a.target), None)
        summ["t_reach_90pct_s"] = t_reach
        summ["overshoot_m"] = round(hmax - a.target, 4)
        # settled: |h - target| < 5 cm from then on
        settle = None
        for t, h in reversed(heights):
            if abs(h - a.target) >= 0.05:
                break
            settle = t
        summ["settled_5cm_at_s"] = settle
        t_end = heights[-1][0]
        hold = [h for t, h in heights if t >= t_end - 10.0]
        if t_reach is not None and t_end - 10.0 > t_reach:
            mean = sum(hold) / len(hold)
            sd = math.sqrt(sum((h - mean) ** 2 for h in hold) / len(hold))
            summ["hold_window_s"] = [round(t_end - 10.0, 2), round(t_end, 2)]
            summ["hold_mean_m"] = round(mean, 4)
            summ["hold_sd_m"] = round(sd, 4)
            summ["hold_min_m"] = round(min(hold), 4)
            summ["hold_max_m"] = round(max(hold), 4)
            summ["hold_mean_error_m"] = round(mean - a.target, 4)
        summ["max_tilt_deg"] = round(max_tilt, 3)
        summ["final_tilt_deg"] = round(final_tilt, 3)
        summ["final_pos"] = [round(c, 4) for c in quad.pos]
    summ["arena_m"] = list(a.arena)
    if min_wall is not None:
        summ["airborne_at_s"] = airborne_t
        summ["min_wall_distance_m"] = round(min_wall[0], 4)
        summ["min_wall_distance_at_s"] = round(min_wall[1], 2)
        summ["min_wall_distance_xy"] = [round(min_wall[2], 3), round(min_wall[3], 3)]
        summ["touched_wall"] = min_wall[0] < a.radius
        summ["wall_approaches"] = approaches
        summ["path_m"] = round(path, 3)
        summ["max_speed_m_s"] = round(max_speed, 3)
        summ["x_span_m"] = [round(v, 3) for v in x_span]
        summ["y_span_m"] = [round(v, 3) for v in y_span]
    print("fake world summary: " + json.dumps(summ), flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(summ, f, indent=1)


if __name__ == "__main__":
    main()
