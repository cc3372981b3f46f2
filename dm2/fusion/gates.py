"""Plausibility gates on live and replayed input: one absurd message costs that message only.

A finite but absurd stamp or pose would otherwise poison what follows it: a stamp 1000 s ahead
raises the sync watermark so every later message is ``late_message``; a flange pose 1e12 mm out
or joints at 1e300 degrees build defects that are not there. :class:`InputGates` checks every
message before anything else sees it (the clock aligner, the sync watermark, the reorder window,
the recording, the reference), so those move only with plausible stamps and poses.

**Stamps** (``implausible_stamp``), per source (the robot, each profiler; layer marks ride on the
robot's clock). A source's first ``stamp_seed`` messages are held and their median seeds its
clock, so one bad first stamp cannot set it. After that a stamp is plausible when it lies within
``stamp_band_s`` of the newest plausible stamp, plus ``stamp_rate_max`` times the host time
since it arrived (live sources; a replay has no host time), so a pause of the stream is no step.
An implausible message is held as a candidate for a clock step: when further implausible
messages agree with it (the same band) for ``stamp_confirm_s`` of their own stamps, the step is
real and the held messages are released, shifted so the source's stamps continue where they
were (a step back would otherwise make every later message late; a step forward would put the
source seconds away from the others). A replay has no host time to tell a step forward from a
pause of the recording, so there a step forward is released as it is (later stages see a gap).
A plausible message ends the candidate: its held messages stay dropped. So a lasting step of a
clock, forward or back, is re-synced within ``stamp_confirm_s`` of process time and loses at
most that. Live, the host's own clock must agree with the step: the candidate's stamps must
have advanced between ``1 / stamp_rate_max`` and ``stamp_rate_max`` times the host time that
passed between its first and newest arrival. Forged stamps sent in a burst (seconds of stamps
in milliseconds) or trickled (a second of stamps over minutes) stay ``implausible_stamp``, and
the source's clock is never re-synced to them.

**Poses** (``implausible_pose``, robot states): the flange position outside the cell's
workspace box ``workspace_B_mm``, a joint beyond ``joint_limits_deg``, or a motion from the
previous plausible state faster than the robot's limits (``max_tcp_speed_mm_s``,
``max_joint_speed_deg_s``, times ``speed_margin``). Five states in a row that agree with one
another but not with the previous plausible one replace it (that one was the outlier).

The ``dropped`` counts of both reasons are exact: held messages that are released again are
not counted.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import replace

import numpy as np

from dm2.core.config import InputGateConfig
from dm2.core.messages import LayerMark, Profile, RobotState
from dm2.core.tolerances import SAME_ANGLE_RAD

log = logging.getLogger(__name__)

MAX_HELD = 4096  # messages held at most per source (seed or step candidate)
POSE_ADOPT = 5  # consistent states in a row that replace an outlying reference pose
JUMP_MM, JUMP_DEG = 2.0, 0.5  # position / joint change always allowed between two states


class _Clock:
    """One source's clock: newest plausible stamp, held seed or step candidate."""

    __slots__ = ("last", "last_arr", "offset", "seed", "cand", "cand_lo", "cand_hi",
                 "cand_arr")

    def __init__(self):
        self.last = None  # newest plausible stamp [s] (offset applied)
        self.last_arr = None  # its arrival [s, host]
        self.offset = 0.0  # [s] subtracted from raw stamps after a step back
        self.seed: list = []
        self.cand: list = []
        self.cand_lo = self.cand_hi = 0.0
        self.cand_arr = None


class InputGates:
    """Stamp and pose plausibility for one stream (see the module docstring).

    ``admit(msg, arrival_s)`` returns the ``(message, arrival_s)`` pairs to pass on now (none,
    the message, or messages held before); ``flush()`` releases the seeds held at the end of a
    stream. :attr:`dropped` counts ``implausible_stamp`` and ``implausible_pose``;
    :attr:`steps` lists the re-synced clock steps.
    """

    def __init__(self, cfg: InputGateConfig | None = None):
        self.cfg = cfg = cfg or InputGateConfig()
        self.dropped: Counter = Counter()
        self.steps: list[dict] = []
        self._clocks: dict[str, _Clock] = {}
        self._ws = tuple(tuple(float(v) for v in c) for c in cfg.workspace_B_mm)  # (lo, hi)
        self._q_lim = tuple((math.radians(a) - SAME_ANGLE_RAD, math.radians(b) + SAME_ANGLE_RAD)
                            for a, b in cfg.joint_limits_deg)
        self._v_max = cfg.max_tcp_speed_mm_s * cfg.speed_margin
        self._w_max = tuple(math.radians(w) * cfg.speed_margin for w in cfg.max_joint_speed_deg_s)
        self._jump_rad = math.radians(JUMP_DEG)
        self._pose_ref = None  # (stamp, position, joints) of the newest plausible state
        self._pose_cand: list = []

    # ------------------------------------------------------------------------------ entry
    def admit(self, msg, arrival_s: float | None = None) -> list:
        if isinstance(msg, RobotState):
            key = "robot"
        elif isinstance(msg, Profile):
            key = msg.sensor_id
        elif isinstance(msg, LayerMark):
            return self._mark(msg, arrival_s)
        else:
            return [(msg, arrival_s)]
        out = self._stamp(key, msg, arrival_s)
        if key != "robot" or not out:
            return out
        return [(m, a) for m, a in out if self._pose_ok(m)]

    def flush(self) -> list:
        """Release every source's held seed (a stream shorter than the seed); step
        candidates still held stay dropped."""
        out = []
        for key, clock in self._clocks.items():
            if clock.seed:
                out.extend(self._seeded(key, clock))
        if out:
            robot = [(m, a) for m, a in out if isinstance(m, RobotState)]
            keep = {id(m) for m, _ in robot if self._pose_ok(m)}
            out = [(m, a) for m, a in out if not isinstance(m, RobotState) or id(m) in keep]
        return out

    # ----------------------------------------------------------------------------- stamps
    def _stamp(self, key: str, msg, arr) -> list:
        clock = self._clocks.get(key)
        if clock is None:
            clock = self._clocks[key] = _Clock()
        if clock.last is None:
            clock.seed.append((msg, arr))
            if len(clock.seed) < self.cfg.stamp_seed:
                return []
            return self._seeded(key, clock)
        cfg = self.cfg
        c = msg.stamp_s - clock.offset
        if self._within(c, clock.last, clock.last_arr, arr):
            if clock.cand:
                clock.cand = []  # a passing outlier (its messages stay dropped)
            if c > clock.last:
                clock.last, clock.last_arr = c, arr
            return [(self._shifted(msg, clock.offset), arr)]
        self.dropped["implausible_stamp"] += 1
        if clock.cand and (clock.cand_lo - cfg.stamp_band_s <= c) and \
                self._within(c, clock.cand_hi, clock.cand_arr, arr):
            clock.cand.append((msg, arr))
            if c > clock.cand_hi:
                clock.cand_hi, clock.cand_arr = c, arr
            clock.cand_lo = min(clock.cand_lo, c)
        else:
            clock.cand = [(msg, arr)]
            clock.cand_lo = clock.cand_hi = c
            clock.cand_arr = arr
        if len(clock.cand) > MAX_HELD:
            del clock.cand[: len(clock.cand) - MAX_HELD]
        if clock.cand_hi - clock.cand_lo >= cfg.stamp_confirm_s and len(clock.cand) >= 3 \
                and self._host_agrees(clock):
            return self._resync(key, clock)
        return []

    def _host_agrees(self, clock: _Clock) -> bool:
        """A live step is confirmed only when the host time that passed over the candidate
        agrees with its stamps: they advanced at most ``stamp_rate_max`` times, and at least
        ``1 / stamp_rate_max`` of, the host time between its first and newest arrival (a burst
        of forged stamps a second apart that arrived within milliseconds is no clock)."""
        a0, a1 = clock.cand[0][1], clock.cand[-1][1]
        if a0 is None or a1 is None:
            return True  # a replay has no host time
        rate = self.cfg.stamp_rate_max
        host_s = a1 - a0
        stamp_s = clock.cand_hi - clock.cand_lo
        return host_s > 0 and host_s / rate <= stamp_s <= host_s * rate

    def _within(self, c: float, ref: float, ref_arr, arr) -> bool:
        band = self.cfg.stamp_band_s
        ahead = band
        if arr is not None and ref_arr is not None and arr > ref_arr:
            ahead += self.cfg.stamp_rate_max * (arr - ref_arr)
        return ref - band <= c <= ref + ahead

    def _seeded(self, key: str, clock: _Clock) -> list:
        """Seed the clock from the median of the held first stamps; release those near it."""
        held, clock.seed = clock.seed, []
        stamps = sorted(m.stamp_s for m, _ in held)
        mid = stamps[(len(stamps) - 1) // 2]  # the (lower) median: one of the held stamps
        out = []
        for m, a in held:
            if abs(m.stamp_s - mid) <= self.cfg.stamp_band_s:
                out.append((m, a))
                if clock.last is None or m.stamp_s > clock.last:
                    clock.last, clock.last_arr = m.stamp_s, a
            else:
                self.dropped["implausible_stamp"] += 1
        return out

    def _resync(self, key: str, clock: _Clock) -> list:
        held, clock.cand = clock.cand, []
        stamps = np.sort([m.stamp_s - clock.offset for m, _ in held])
        diffs = np.diff(stamps)
        period = float(np.median(diffs[diffs > 0])) if np.any(diffs > 0) else 0.0
        step = float(stamps[0] - clock.last) - period  # the clock's jump (less one period)
        live = held[0][1] is not None
        if step < 0 or live:  # continue the source's stamps where they were
            clock.offset += step
        self.dropped["implausible_stamp"] -= len(held)
        self.steps.append({"source": key, "step_s": round(step, 6),
                           "at_s": round(float(clock.last), 6), "held": len(held)})
        log.warning("the clock of %s stepped %+.3f s at %.3f s: re-synced (%d messages held)",
                    key, step, clock.last, len(held))
        out = [(self._shifted(m, clock.offset), a) for m, a in held]
        top = max(out, key=lambda ma: ma[0].stamp_s)
        clock.last, clock.last_arr = top[0].stamp_s, top[1]
        if key == "robot":
            self._pose_ref = None  # the held states start the pose check afresh
            self._pose_cand = []
        return out

    @staticmethod
    def _shifted(msg, offset: float):
        if offset == 0.0:
            return msg
        stamp = max(0.0, msg.stamp_s - offset)
        if isinstance(msg, RobotState):
            return RobotState.trusted(stamp, msg.seq, msg.joints_rad, msg.T_B_F)
        return replace(msg, stamp_s=stamp)

    def _mark(self, msg: LayerMark, arr) -> list:
        clock = self._clocks.get("robot")
        if clock is None or clock.last is None:
            return [(msg, arr)]
        c = msg.stamp_s - clock.offset
        if clock.cand and clock.cand_lo - self.cfg.stamp_band_s <= c <= \
                clock.cand_hi + self.cfg.stamp_band_s:
            clock.cand.append((msg, arr))  # on the stepped clock: released with its states
            self.dropped["implausible_stamp"] += 1
            return []
        if not self._within(c, clock.last, clock.last_arr, arr):
            self.dropped["implausible_stamp"] += 1
            return []
        return [(self._shifted(msg, clock.offset), arr)]

    # ------------------------------------------------------------------------------ poses
    def _pose_ok(self, s) -> bool:
        """Workspace, joint limits and speed from the previous plausible state (plain floats:
        a few microseconds per state, at 2,500 states a second in a 10x rehearsal)."""
        if not isinstance(s, RobotState):
            return True
        T = s.T_B_F
        px, py, pz = float(T[0, 3]), float(T[1, 3]), float(T[2, 3])
        q = s.joints_rad.tolist()
        (x0, y0, z0), (x1, y1, z1) = self._ws
        ok = x0 <= px <= x1 and y0 <= py <= y1 and z0 <= pz <= z1 and len(q) == len(self._q_lim)
        if ok:
            for v, (a, b) in zip(q, self._q_lim, strict=True):
                if not a <= v <= b:
                    ok = False
                    break
        if not ok:
            self.dropped["implausible_pose"] += 1
            return False
        p = (px, py, pz)
        ref = self._pose_ref
        state = (s.stamp_s, p, q)
        if ref is None or self._consistent(ref, state):
            self._pose_ref = state
            if self._pose_cand:
                self._pose_cand = []
            return True
        self.dropped["implausible_pose"] += 1
        cand = self._pose_cand
        if cand and self._consistent(cand[-1], state):
            cand.append(state)
        else:
            cand[:] = [state]
        if len(cand) >= POSE_ADOPT:  # the reference was the outlier
            self._pose_ref = cand[-1]
            self._pose_cand = []
        return False

    def _consistent(self, ref, state) -> bool:
        dt = abs(state[0] - ref[0])  # reordered states compare just as well
        p, rp = state[1], ref[1]
        d2 = (p[0] - rp[0]) ** 2 + (p[1] - rp[1]) ** 2 + (p[2] - rp[2]) ** 2
        if d2 > (self._v_max * dt + JUMP_MM) ** 2:
            return False
        jump = self._jump_rad
        for a, b, w in zip(state[2], ref[2], self._w_max, strict=True):
            if abs(a - b) > w * dt + jump:
                return False
        return True
