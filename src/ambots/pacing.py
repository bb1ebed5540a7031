"""The firmware's pace tied to what a real controller has executed
(``driver:=trajectory``), without ROS.

On the wall clock alone the runner reports a G-code line as done when the
*plan* says so.  A controller that executes slower than commanded (a UR's
speed scaling at 70 %) or stops (a protective stop) leaves the arm behind
those reports, and a report releases another arm's barrier (A9) while this
arm is still in the space the barrier protects.  Here the runner's clock,
the chunks' stamps and the messages that leave the firmware follow the
controller's joint states instead.

:class:`Progress` -- how far along the commanded motion the arm really is.
The commanded samples handed to the controller (runner time ``c``,
joints) are kept.  A measured joint vector is matched against the
polyline through them: the nearest point, looked for only from the last
match on and no further than the arm can have moved since (``rate`` x the
time since the last match, at least ``window`` s of motion; rests between
two stretches of motion count as nothing), accepted if it is within
``tolerance`` (rad, largest joint); of equally near points the latest
(where the arm rests, every sample of the rest is where it is).  Its
runner time is the progress ``pi``, which never goes back; a measurement
that matches nothing (the arm is not on the commanded path) leaves it
where it is.  Where the commanded motion at the match moves (faster than
``moving_speed``), the match also gives the *lag*: the measurement's ROS
time minus ``pi``, i.e. when the controller executes runner time ``pi``;
:meth:`Progress.lag_now` carries it on to a later instant at the rate the
progress made over the last ``span`` s (a controller at 70 % falls 0.3 s
behind per second, a stopped one 1 s).

:class:`Pacer` -- the firmware's clock, the stamps and the outgoing gate:

* **Clock.**  The runner's time ``R`` never runs faster than the wall.
  While commanded motion is pending (the arm has not reached the last
  sample sent) it stays within ``lead`` of the arm's progress:
  ``R <= pi + lead``; so the stream, which sends up to ``ahead`` s past
  ``R``, never has more than ``lead + ahead`` + one chunk of motion queued
  at the controller.  With nothing pending (the arm rests where the
  commanded motion ended) ``R`` advances at the wall's rate but is not
  moved forward to catch up with it: a block started from there would be
  executed at once.  So after a stall the runner's time, and the M word of
  its reports, stay behind the wall by the time the arm lost.  Without
  any joint states from the controller (none ever received), ``R`` is the
  wall, as before this module.
* **Stamps.**  The sample at runner time ``c`` is stamped ``c + shift``
  (ROS time).  A stretch of motion that starts with nothing pending gets
  ``shift = wall - R + lead``: its first sample ``lead`` s after it is
  sent.  Otherwise the shift stays unless the measured lag (from a match
  within the last ``max_age`` s) differs from it by more than ``resync``
  s (within a stretch: exceeds it; a controller never runs ahead of its
  commands): then the chunk gets ``shift = lag``.  Why that is seamless:
  a ros_control joint trajectory controller maps a trajectory's stamp onto
  its own time when the trajectory arrives (its uptime + stamp - now), and
  the UR's scaled controller advances that time at its speed scaling (0
  in a protective stop, and it continues from there on resume).  A chunk
  that arrives at ``a`` and must start where the queued motion ends
  (runner time ``c``) needs the stamp ``a + (c - pi(a))``, and the lag
  ``t - pi(t)`` measured while the arm moves is exactly that shift.  A
  stretch that starts from rest is never stamped less than ``min_lead`` s
  ahead.
* **Gate.**  A message the runner produced at its time ``T`` leaves the
  firmware only when ``pi >= T`` (or nothing is pending): reports that
  release other arms' barriers follow the arm, not the plan.

:class:`ControllerModel` -- that controller as a model (the rostest's
stand-in controllers and the unit tests run it): its own time advances
at ``rate`` per second (1/``time_scale``; 0 while stopped), stamps are
mapped at arrival, a trajectory replaces what is queued from its first
point on, positions are interpolated linearly between points, before the
first point it holds where it is and after the last it holds the last.

Units: seconds (runner time and ROS time), radians.
"""
import math
from collections import deque

import numpy as np

__all__ = ["Progress", "Pacer", "ControllerModel"]

#: runner times closer than this (s) are the same instant
EPS = 1e-9
NS = 1000000000


class Progress:
    """Where along the commanded samples the arm is (see the module docstring).

    Parameters
    ----------
    sample_period : s between the samples of a stretch of motion
    tolerance : rad (largest joint) a measurement may be off the commanded path
    window : s of motion a match may always move forward
    rate : how much faster than the elapsed time a match may move forward
    moving_speed : rad/s (largest joint) above which the commanded motion at a match moves
    tie : rad; points this much nearer than the nearest count as equally near
    span : s of matches over which the rate of progress is measured
    """

    def __init__(self, sample_period, tolerance=0.01, window=0.05, rate=1.5, moving_speed=1e-4, tie=1e-6,
                 span=0.2):
        self.dt = float(sample_period)
        self.tolerance, self.window, self.rate = float(tolerance), float(window), float(rate)
        self.moving_speed, self.tie = float(moving_speed), float(tie)
        self._c = np.zeros(0)            # runner times of the samples kept
        self._m = np.zeros(0)            # motion time: runner time without the rests between stretches
        self._Q = None
        self._i = 0                      # segment (sample i -> i + 1) of the last match
        self.first = None                #: runner time of the first sample ever added
        self.pi = None                   #: runner time the arm has reached (None: no match yet)
        self.lag = None                  #: s, ROS time - runner time at the last match in motion
        self.lag_at = None               #: ROS time of that match
        self.moving = False              #: whether the last match was in motion
        self.matched_at = None           #: ROS time of the last match
        self.measured_at = None          #: ROS time of the last measurement
        self.misses = 0                  #: measurements in a row that matched nothing
        self.span = float(span)
        self._track = deque()            # (ROS time, progress) of the recent matches
        self._since = None               # ROS time of the first measurement against samples

    @property
    def end(self):
        """Runner time of the last sample (None: none yet)."""
        return float(self._c[-1]) if len(self._c) else None

    def add(self, c, Q):
        """Commanded samples: runner times ``c`` (M,) increasing, joints
        ``Q`` (M, n).  Samples not later than the last one are the same
        samples again (a chunk starts with the previous one's last)."""
        c = np.asarray(c, float)
        Q = np.atleast_2d(np.asarray(Q, float))
        if self._Q is None:
            self._Q = np.zeros((0, Q.shape[1]))
            self.first = float(c[0])
        if len(self._c):
            keep = c > self._c[-1] + EPS
            c, Q = c[keep], Q[keep]
        if not len(c):
            return
        step = np.diff(np.concatenate([self._c[-1:], c])) if len(self._c) else np.concatenate([[0.0], np.diff(c)])
        step = np.where(step <= 1.5 * self.dt, step, 0.0)          # a rest between two stretches: no motion time
        m0 = self._m[-1] if len(self._m) else 0.0
        self._c = np.concatenate([self._c, c])
        self._m = np.concatenate([self._m, m0 + np.cumsum(step)])
        self._Q = np.concatenate([self._Q, Q])

    def rate_of_progress(self):
        """Runner seconds per second the arm progressed over the last
        ``span`` s of matches (0..1), or None when that is too short."""
        if len(self._track) < 2:
            return None
        (t0, p0), (t1, p1) = self._track[0], self._track[-1]
        if t1 - t0 < 0.25 * self.span:
            return None
        return min(1.0, max(0.0, (p1 - p0) / (t1 - t0)))

    def lag_now(self, t):
        """The lag (s) carried on to ROS time ``t`` (None: no lag measured)."""
        if self.lag is None:
            return None
        r = self.rate_of_progress()
        return self.lag + (1.0 - (1.0 if r is None else r)) * max(0.0, t - self.lag_at)

    def measure(self, t, q):
        """A measured joint vector ``q`` at ROS time ``t``: returns the
        progress (runner time) or None if it matches nothing."""
        self.measured_at = t
        if not len(self._c):
            return None
        q = np.asarray(q, float)
        c, m, Q = self._c, self._m, self._Q
        i0 = self._i
        since = self.matched_at if self.matched_at is not None else self._since
        if since is None:
            self._since = since = t
        reach = max(self.window, self.rate * (t - since))
        hi = int(np.searchsorted(m, m[i0] + reach, side="right"))
        hi = min(max(hi, i0 + 2), len(c))
        if hi - i0 < 2:                  # one sample
            j, u = np.array([i0]), np.array([0.0])
            P = Q[i0:i0 + 1]
            X = P
        else:
            j = np.arange(i0, hi - 1)
            P = Q[j]
            D = Q[j + 1] - P
            dd = np.einsum("ij,ij->i", D, D)
            u = np.where(dd > 0, np.einsum("ij,ij->i", q - P, D) / np.where(dd > 0, dd, 1.0), 1.0)
            u = np.clip(u, 0.0, 1.0)
            X = P + u[:, None] * D
        d = np.abs(q - X).max(axis=1)
        dmin = float(d.min())
        if dmin > self.tolerance:
            self.misses += 1
            return None
        k = int(np.nonzero(d <= dmin + self.tie)[0][-1])           # the latest of the nearest
        jk, uk = int(j[k]), float(u[k])
        self.misses = 0
        self.matched_at = t
        if jk + 1 >= len(c):
            here, speed = float(c[jk]), 0.0
        else:
            span = float(c[jk + 1] - c[jk])
            if span <= 1.5 * self.dt:
                here = float(c[jk]) + uk * span
                speed = float(np.abs(Q[jk + 1] - Q[jk]).max()) / span
            else:                         # across a rest between two stretches
                here, speed = float(c[jk + 1] if uk >= 0.5 else c[jk]), 0.0
        self.moving = speed > self.moving_speed
        if self.moving:
            self.lag, self.lag_at = t - here, t
        self.pi = here if self.pi is None else max(self.pi, here)
        self._track.append((t, self.pi))
        while len(self._track) > 2 and self._track[1][0] <= t - self.span:
            self._track.popleft()
        self._i = jk + 1 if uk >= 1.0 and jk + 2 < len(c) else jk
        if self._i > 1:                   # forget what is behind
            drop = self._i - 1
            self._c, self._m, self._Q = self._c[drop:], self._m[drop:], self._Q[drop:]
            self._i = 1
        return self.pi


class Pacer:
    """The firmware's clock, the chunks' stamps and the gate of its
    messages, tied to the controller's joint states (see the module
    docstring).

    Parameters
    ----------
    sample_period : s between trajectory points
    lead : s the runner may run ahead of the arm's progress (the firmware's ``command_delay``)
    tolerance : rad a measured joint vector may be off the commanded path (:class:`Progress`)
    resync : s the measured lag may differ from the stamps' shift before chunks are stamped anew
    min_lead : s; a stretch starting from rest is never stamped closer to the present than this
    max_age : s a lag measurement is used for
    tie : False: measure, but keep the runner on the wall and the gate open
        (the firmware before this module; for comparisons)
    """

    def __init__(self, sample_period, lead=0.3, tolerance=0.01, resync=0.005, min_lead=0.05, max_age=0.5,
                 tie=True):
        self.tie = bool(tie)
        self.progress = Progress(sample_period, tolerance)
        self.dt = float(sample_period)
        self.dt_ns = int(round(self.dt * NS))
        self.lead, self.resync = float(lead), float(resync)
        self.min_lead, self.max_age = float(min_lead), float(max_age)
        self.R = None                     #: the runner's time
        self._wall = None
        self.shift = None                 #: s, ROS time - runner time of the samples being sent
        self.closed = False               #: a controller's joint state has come
        self.resyncs = 0                  #: chunks stamped anew from the measured lag
        self._stamp0 = (None, None, 0)    # (segment, shift, ns of its sample 0)
        self.last_ns = 0                  #: stamp (ns) of the last point

    # ----------------------------------------------------------- measurements
    def measured(self, t, q):
        """The controller's joint vector ``q`` at ROS time ``t``."""
        self.closed = self.tie
        self.progress.measure(t, q)

    def pending(self):
        """Whether commanded motion is still ahead of the arm."""
        p = self.progress
        if p.end is None:
            return False
        at = p.pi if p.pi is not None else p.first
        return at < p.end - EPS

    def released_until(self):
        """Messages the runner produced up to this runner time may leave."""
        if not self.closed or not self.pending():
            return math.inf
        p = self.progress
        return p.pi if p.pi is not None else p.first

    # ----------------------------------------------------------- the clock
    def clock(self, wall):
        """The runner's time at ROS time ``wall`` (call once per firmware step)."""
        if self.R is None:
            self.R, self._wall = float(wall), float(wall)
            return self.R
        dt = max(0.0, wall - self._wall)
        self._wall = max(self._wall, wall)
        if not self.closed:
            self.R = max(self.R, wall)
        elif self.pending():
            p = self.progress
            at = p.pi if p.pi is not None else p.first
            self.R = max(self.R, min(self.R + dt, at + self.lead))
        else:
            self.R += dt
        return self.R

    # ----------------------------------------------------------- stamps
    def stamp(self, c, Q, new_stretch, wall):
        """The shift (ROS time - runner time) of a chunk of samples at runner
        times ``c`` (M,) with joints ``Q`` (M, n), sent at ROS time ``wall``;
        ``new_stretch``: its first sample starts a stretch from rest.  The
        samples are then the commanded motion the arm is measured against."""
        p = self.progress
        fresh = new_stretch and (not self.closed or not self.pending())
        if self.shift is None or fresh:
            self.shift = wall - (self.R if self.R is not None else wall) + self.lead
        elif self.closed and p.moving and p.lag is not None and wall - p.lag_at <= self.max_age:
            lag = p.lag_now(wall)
            grow = lag - self.shift
            if grow > self.resync or (new_stretch and abs(grow) > self.resync):
                self.shift = lag
                self.resyncs += 1
        if new_stretch:
            self.shift = max(self.shift, wall + self.min_lead - float(c[0]))
        p.add(c, Q)
        return self.shift

    def stamps(self, chunk, wall):
        """The stamps (ROS time, ns, int64 (M,)) of the points of a
        :class:`~ambots.trajectory.Chunk` sent at ROS time ``wall`` (s):
        :meth:`stamp` on its runner times, the points of one stretch every
        ``sample_period`` from its sample 0 (moved when stamped anew), a new
        stretch never before the last point sent."""
        seg = chunk.segment
        idx = chunk.first + np.arange(len(chunk.q))
        new = self._stamp0[0] is not seg
        shift = self.stamp(seg.start_time + idx * self.dt, chunk.q, new, wall)
        if new:
            self._stamp0 = (seg, shift, max(int(round((seg.start_time + shift) * NS)), self.last_ns))
        elif shift != self._stamp0[1]:
            self._stamp0 = (seg, shift, int(round((seg.start_time + shift) * NS)))
        t_ns = self._stamp0[2] + idx.astype(np.int64) * self.dt_ns
        self.last_ns = max(self.last_ns, int(t_ns[-1]))
        return t_ns

    def stats(self):
        p = self.progress
        return {"closed_loop": self.closed, "resyncs": self.resyncs,
                "behind_wall_s": None if self.R is None else round(self._wall - self.R, 4),
                "progress": None if p.pi is None else round(p.pi, 4), "unmatched": p.misses}


class ControllerModel:
    """A ros_control joint trajectory controller, as the firmware is designed
    against (see the module docstring): ``command`` a trajectory, ``advance``
    its own time, read ``q``.  ``now`` and stamps: ROS time, s."""

    def __init__(self, q0, now):
        self.q = np.array(q0, dtype=float)
        self.now = float(now)
        self.uptime = float(now)          #: the controller's own time
        self.t = np.zeros(0)              # points, in the controller's time
        self.Q = np.zeros((0, len(self.q)))
        self.splice = None                #: s of queued motion the last trajectory cut (see command)

    def command(self, now, stamp, tfs, Q):
        """A trajectory arrives at ``now`` (the controller advanced to it):
        ``stamp`` (0: start now), points at ``tfs`` (M,) s from it with
        positions ``Q`` (M, n)."""
        start = self.uptime + (stamp - now if stamp > 0 else 0.0)
        ts = start + np.asarray(tfs, float)
        Q = np.atleast_2d(np.asarray(Q, float))
        # a trajectory that starts with a queued point (a chunk starts with the previous one's
        # last): how much of the queued motion it cuts (s of the controller's time; < 0: a wait)
        same = np.nonzero(np.abs(self.Q - Q[0]).max(axis=1) <= 1e-9)[0] if len(self.t) else ()
        self.splice = float(self.t[same[-1]] - ts[0]) if len(same) else None
        keep = self.t < ts[0]
        t, P = self.t[keep], self.Q[keep]
        if not len(t) and ts[0] > self.uptime:       # from where it is to the first point
            t, P = np.array([self.uptime]), self.q[None]
        self.t = np.concatenate([t, ts])
        self.Q = np.concatenate([P, Q])

    def advance(self, now, rate=1.0):
        """To ROS time ``now``, the controller's time at ``rate`` per second
        since the last call; returns the joints."""
        self.uptime += max(0.0, now - self.now) * rate
        self.now = max(self.now, float(now))
        t = self.t
        if len(t):
            u = self.uptime
            if u >= t[-1]:
                self.q = self.Q[-1].copy()
            elif u > t[0]:
                k = int(np.searchsorted(t, u, side="right")) - 1
                a = (u - t[k]) / (t[k + 1] - t[k])
                self.q = self.Q[k] + a * (self.Q[k + 1] - self.Q[k])
            k = int(np.searchsorted(t, u, side="right")) - 1
            if k > 0:                     # forget the points passed
                self.t, self.Q = t[k:], self.Q[k:]
        return self.q.copy()
