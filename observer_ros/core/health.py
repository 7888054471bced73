# observer_ros.core.health: is the loop healthy? Divergence, overload, pole margins.
"""
Checks the nodes run on their own numbers: a plausible envelope, a load meter, pole margins.

No rclpy here: the nodes feed these with their estimates, commands and wall times, and
publish what they find on /diagnostics.

"""

import operator
import time

import numpy as np

__all__ = ['ENVELOPE_FACTOR', 'ENVELOPE_LEARN_CAP', 'ENVELOPE_LEARN_S', 'ENVELOPE_PERSIST',
           'Envelope', 'state_scale', 'divergence_envelopes', 'WorkBudget', 'HeldOff',
           'PARAMETER_SHARE', 'PARAMETER_WINDOW',
           'LoadMeter', 'max_prediction_gap', 'SettleCheck', 'pole_margin_problem',
           'settling_time', 'POLE_SLOWEST', 'POLE_FASTEST']

# A value this many times beyond the plausible scale is divergence, not a transient.
ENVELOPE_FACTOR = 100.0
# Seconds (on the values' own time base) during which the envelope learns the run's scale.
ENVELOPE_LEARN_S = 3.0
# Consecutive values beyond the bound, none smaller than the one before, that make a
# divergence: a single outlier is not one (the command gate or the limits handle it).
ENVELOPE_PERSIST = 5
# What it learns is capped at this many times the file's scale (a divergence that starts
# at once cannot teach it that a growing value is plausible).
ENVELOPE_LEARN_CAP = 10.0
# Parameter changes may take at most this share of a node's time over this window (s):
# a redesign costs a node tenths of a second, and estimation comes first.
PARAMETER_SHARE = 0.03
PARAMETER_WINDOW = 10.0
# Pole margins: no pole slower than the plant's slowest non-zero mode / POLE_SLOWEST, none
# faster than POLE_FASTEST / sample time (exp(-5) per step: faster is not realised).
POLE_SLOWEST = 100.0
POLE_FASTEST = 5.0


class Envelope:
    """
    Flag a vector that grew beyond what the model and the first seconds make plausible.

    The plausible magnitude of component i is ``max(scale_i, seen_i)``, where ``scale``
    comes from the vehicle file (initial state, reference, input limits) and ``seen_i`` is
    the largest magnitude of the first ``learn`` seconds, capped at
    :data:`ENVELOPE_LEARN_CAP` times ``scale_i`` (so a divergence that starts at once is not
    learned). Divergence is ``persist`` consecutive values beyond ``factor`` times it, each
    at least as far beyond as the one before (growing); a value that is not finite is
    divergence at once.

    Parameters
    ----------
    names : sequence of str
        Component names (reported).
    scale : array_like
        Plausible magnitudes from the file; zeros take the largest of them (or 1).
    what : str
        What the vector is (``x_hat``, ``u``), for the report.
    factor, learn : float
        See :data:`ENVELOPE_FACTOR` and :data:`ENVELOPE_LEARN_S`.
    persist : int
        See :data:`ENVELOPE_PERSIST`.

    """

    def __init__(self, names, scale, what, factor=ENVELOPE_FACTOR, learn=ENVELOPE_LEARN_S,
                 persist=ENVELOPE_PERSIST):
        scale = np.abs(np.asarray(scale, dtype=float))
        scale = np.where(np.isfinite(scale), scale, 0.0)
        top = scale.max() if scale.size and scale.max() > 0.0 else 1.0
        self.names = list(names)
        self.scale = self.file_scale = np.where(scale > 0.0, scale, top)
        self.what = what
        self.factor = float(factor)
        self.learn = float(learn)
        self.persist = int(persist)
        self.reset()

    def reset(self):
        """Start learning again from the file's scale (a clock that starts over)."""
        self.rebase(None)

    def rebase(self, value):
        """
        Start learning again from the magnitudes of ``value`` (or the file's scale if None).

        After an outage the plant may really be far from where the run started: what is
        plausible is judged from where the loop closes again.
        """
        self.scale = self.file_scale if value is None else np.maximum(
            self.file_scale, np.where(np.isfinite(value), np.abs(value), 0.0))
        self._t0 = None
        self._seen = np.zeros_like(self.scale)
        self._beyond = 0            # consecutive growing values beyond the bound
        self._last_ratio = 0.0
        self._fixed_bound = None    # the bound as floats, once learning is over

    @property
    def bound(self):
        """Return the magnitudes beyond which a component is divergence (ndarray)."""
        return self.factor * np.maximum(self.scale, self._seen)

    def inside(self, value):
        """
        Tell whether every component of ``value`` is finite and within :attr:`bound`.

        Stricter than :meth:`check`, which lets a few values beyond the bound pass (a
        transient): for deciding that a loop closed again after an outage is back.
        """
        fixed = self._fixed_bound
        if fixed is not None:
            # learnt: plain floats (a NaN fails <=)
            values = value.tolist() if isinstance(value, np.ndarray) else value
            return len(values) == len(fixed) and all(map(operator.le, map(abs, values), fixed))
        mag = np.abs(np.asarray(value, dtype=float))
        return bool(np.all(np.isfinite(mag)) and np.all(mag <= self.bound))

    def check(self, t, value):
        """
        Return None if ``value`` at time t is plausible, else a one-line report.

        Parameters
        ----------
        t : float
            Time of the value, s.
        value : array_like
            The vector.

        Returns
        -------
        problem : str or None
            Names the component, its value and the bound.

        """
        fixed = self._fixed_bound
        if fixed is not None and not self._beyond:
            # learnt, and nothing beyond: plain floats, about 1 us per call on a 3-vector
            # against 6-7 us for the numpy below; a NaN fails <= and goes on below
            values = value.tolist() if isinstance(value, np.ndarray) else value
            if all(map(operator.le, map(abs, values), fixed)):
                return None
        mag = np.abs(np.asarray(value, dtype=float))
        bound = self.bound
        ratio = np.where(np.isfinite(mag), mag / bound, np.inf)
        i = int(np.argmax(ratio))
        if ratio[i] > 1.0:
            if ratio[i] >= self._last_ratio:
                self._beyond += 1
            self._last_ratio = ratio[i]
            if self._beyond < self.persist and np.isfinite(ratio[i]):
                return None
            return (f'{self.what} {self.names[i]} = {float(value[i]):.3g} beyond the '
                    f'plausible +-{bound[i]:.3g} ({self.factor:g} x what the file and '
                    f'the first {self.learn:g} s make plausible)')
        self._beyond, self._last_ratio = 0, 0.0
        if self._t0 is None:
            self._t0 = t
        if t - self._t0 <= self.learn:
            np.maximum(self._seen, np.minimum(mag, ENVELOPE_LEARN_CAP * self.scale),
                       out=self._seen)
        elif fixed is None and len(mag) == len(self.scale):
            self._fixed_bound = bound.tolist()
        return None


def state_scale(vehicle, x_d=None):
    """Return the plausible magnitude of each state from the file (initial values, x_d)."""
    n = vehicle.plant.n
    parts = [np.zeros(n)]
    for v in (vehicle.simulator.initial_state, vehicle.observer.initial_estimate, x_d,
              vehicle.controller.reference):
        if v is not None:
            parts.append(np.abs(np.asarray(v, dtype=float)))
    return np.max(parts, axis=0)


def divergence_envelopes(vehicle, K, x_d, Kd, persist=ENVELOPE_PERSIST):
    """
    Return the envelopes of the estimate and of the command (before its limits).

    The state's scale is :func:`state_scale`'s (zeros take the largest, or 1). The
    command's scale is the file's input limits where given, else ``|K|`` applied to the
    states' scale plus ``|x_d|`` (and ``|Kd x_d|``): without limits, 100 times that
    (:data:`ENVELOPE_FACTOR`) is the largest command the compensator sends. ``persist``:
    see :class:`Envelope` (1: every value beyond the bound is reported).
    """
    plant = vehicle.plant
    K, x_d, Kd = (np.asarray(a, dtype=float) for a in (K, x_d, Kd))
    xs = Envelope(plant.state_names, state_scale(vehicle, x_d), 'x_hat', persist=persist)
    x_scale = xs.scale
    u_scale = np.abs(K) @ (x_scale + np.abs(x_d)) + np.abs(Kd @ x_d)
    c = vehicle.controller
    for limit in (c.u_min, c.u_max):
        if limit is not None:
            lim = np.abs(np.asarray(limit, dtype=float))
            u_scale = np.where(np.isfinite(lim), np.maximum(u_scale, lim), u_scale)
    return xs, Envelope(plant.input_names, u_scale, 'u', persist=persist)


class LoadMeter:
    """
    Measure whether a node keeps up with its input.

    The node reports each message it takes (the wall time it started and ended) and the
    messages it knows were missed (gaps in a sensor's stamps). The busy fraction of a
    window is the CPU time of the thread that handles the messages (``cpu_clock``, read
    when a window opens and closes) over the window's wall time: the callbacks and the
    executor's own work between them (taking, deserialising and dispatching each message:
    most of a small rclpy node's time), but not the time it waits for input. A node whose
    queue only grows is busy all the time. Over a window, a busy fraction at or above
    ``busy_limit``, or any missed message, is overload. (A thread starved of CPU by other
    processes reads less busy than it is; its sensor queue, bounded, then drops messages,
    and the gaps in their stamps say so.)

    (The pauses between messages are no measure of it: at 1 kHz a node that answers each
    message in 0.3 ms waits 0.7 ms for the next, less than the executor's overhead per
    message at lower rates; taken as busy, a healthy 1 kHz observer read 95 % busy.)

    Parameters
    ----------
    window : float
        Wall seconds per verdict.
    busy_limit : float
        Busy fraction at and above which the node is overloaded.
    cpu_clock : callable, optional
        Seconds of CPU time of the calling thread; default :func:`time.thread_time` (call
        :meth:`took` from the thread that spins the node).

    """

    def __init__(self, window=0.5, busy_limit=0.9, cpu_clock=time.thread_time):
        self.window = float(window)
        self.busy_limit = float(busy_limit)
        self._cpu_clock = cpu_clock
        self._start = self._last_end = self._cpu_start = None
        self._answered = self._missed = 0
        self.rate = self.missed_rate = self.busy = None
        self.overloaded = False

    def took(self, start, end, missed=0):
        """
        Note one message handled from wall time ``start`` to ``end``, after ``missed`` lost.

        Returns
        -------
        verdict : bool
            True when this message closed a window (``rate``, ``missed_rate``, ``busy``
            and ``overloaded`` are new).

        """
        if self._start is None:
            self._start, self._cpu_start = start, self._cpu_clock()
        self._last_end = end
        self._answered += 1
        self._missed += missed
        span = end - self._start
        if span < self.window:
            return False
        cpu = self._cpu_clock()
        self.rate = self._answered / span
        self.missed_rate = self._missed / span
        self.busy = min(1.0, max(0.0, (cpu - self._cpu_start) / span))
        self.overloaded = self.busy >= self.busy_limit or self._missed > 0
        self._start, self._cpu_start, self._answered, self._missed = end, cpu, 0, 0
        return True

    def missed(self, count):
        """Note ``count`` messages known to be lost (a gap in a sensor's stamps)."""
        self._missed += count

    def idle(self, now):
        """Forget a window with no message for two windows (the input stopped)."""
        if self._last_end is not None and now - self._last_end > 2.0 * self.window:
            self._start = self._last_end = self._cpu_start = None
            self._answered, self._missed = 0, 0
            self.overloaded = False


class WorkBudget:
    """
    Admit a kind of work (a node's parameter changes) while it takes little of the time.

    Each piece of work admitted is timed (:meth:`spent`: the CPU time of the thread that
    ran it, so that a host busy with other processes does not count against the node); a
    new one is admitted while the work of the last ``window`` seconds took less than
    ``share`` of them (the first one after a quiet window always: one redesign may take
    longer than the share, and the next waits until it has left the window). A refusal
    costs nothing but this check.

    Parameters
    ----------
    share : float
        Fraction of the time, 0 < share <= 1.
    window : float
        Seconds over which it is measured.

    """

    def __init__(self, share=PARAMETER_SHARE, window=PARAMETER_WINDOW):
        self.share, self.window = float(share), float(window)
        self._work = []             # (end, seconds), oldest first

    def _forget(self, now):
        work = self._work
        while work and work[0][0] < now - self.window:
            work.pop(0)

    def used(self, now):
        """Return the seconds of work within the window ending at ``now``."""
        self._forget(now)
        return sum(seconds for _, seconds in self._work)

    def refuse(self, now):
        """
        Return why new work is refused at ``now`` (the reason), or None to admit it.

        The reason names the time taken, the window, the share and when to try again.
        """
        used = self.used(now)
        allowed = self.share * self.window
        if used < allowed:
            return None
        # when enough of the oldest work has left the window
        wait, left = 0.0, used
        for end, seconds in self._work:
            left -= seconds
            wait = end + self.window - now
            if left < allowed:
                break
        return (f'busy: parameter changes took {1e3 * used:.0f} ms of the last '
                f"{self.window:g} s, at most {100 * self.share:g} % of the node's time "
                f'(estimation and control first); try again in {max(wait, 0.0):.1f} s')

    def spent(self, seconds, end):
        """Note work of ``seconds`` that ended at ``end`` (monotonic seconds)."""
        self._forget(end)
        self._work.append((end, max(0.0, seconds)))


class HeldOff:
    """
    Tell a watchdog's check that comes after its process was held off the CPU.

    A watchdog that runs on a timer checks every period. A check that comes more than
    ``gap`` seconds after the one before shows that the process did not run meanwhile
    (stopped, or starved of the CPU): whatever reached it since waits in its queue, taken
    after this check, so the check must judge nothing (a timeout now would be the
    process's own, not its peers'). The next check, one period later, judges, on the
    caller's terms: the compensator judges the estimate's age as it is (in a realtime loop
    an observer that is really gone must not be waited for longer), the lock-step
    observer starts its wait for the command again (core.lockstep_wait: there waiting
    longer costs nothing, and giving up early changes the run).

    """

    def __init__(self):
        self._last = None

    def check(self, now, gap):
        """
        Note a check at ``now`` (wall seconds); return True when it must judge nothing.

        ``gap``: seconds since the check before beyond which this one judges nothing.
        """
        last, self._last = self._last, now
        return last is not None and now - last > gap


class SettleCheck:
    """
    Tell when an observer has settled again: its estimates follow the model step by step.

    While it converges its corrections are large; once settled, ``x_k`` agrees with
    ``Ad x_{k-1} + Bd u_{k-1}`` within ``tol`` times each state's scale, ``count`` times
    in a row (only consecutive estimates one sample time apart are compared). An
    innovation-consistency test that needs no access to the observer's residual.

    Parameters
    ----------
    Ad, Bd : ndarray
        The model over one sample time.
    dt : float
        The sample time, s.
    scale : array_like
        Each state's scale (the divergence envelope's).
    tol : float
        Allowed one-step mismatch, in units of the scale.
    count : int
        Consecutive consistent estimates needed.

    """

    def __init__(self, Ad, Bd, dt, scale, tol=0.1, count=10):
        self.Ad, self.Bd, self.dt = Ad, Bd, float(dt)
        self.scale = np.asarray(scale, dtype=float)
        self.tol, self.count = float(tol), int(count)
        self.start(np.inf)

    def start(self, deadline):
        """Start watching; give up waiting (settled) at time ``deadline``."""
        self.deadline = deadline
        self._prev = None
        self._ok = 0

    def settled(self, t, x_hat, u):
        """Note the estimate at t and the command sent for it; return True once settled."""
        ok = False
        if self._prev is not None and abs(t - self._prev[0] - self.dt) < 1e-3 * self.dt:
            _, x_prev, u_prev = self._prev
            pred = self.Ad @ x_prev + self.Bd @ u_prev
            ok = bool(np.max(np.abs(np.asarray(x_hat) - pred) / self.scale) < self.tol)
        self._ok = self._ok + 1 if ok else 0
        self._prev = (t, np.array(x_hat, dtype=float), np.array(u, dtype=float))
        return self._ok >= self.count or t >= self.deadline


def max_prediction_gap(A, dt, discrete=False, factor=ENVELOPE_FACTOR):
    """
    Return the longest open-loop prediction, s, over which no mode grows ``factor`` times.

    An estimate predicted further than this (an observer paused for seconds on an unstable
    plant) has its error multiplied by more than ``factor``: it is no estimate any more.

    Parameters
    ----------
    A : (n, n) array_like
        The plant's state matrix (discrete: per sample).
    dt : float
        The sample time, s.
    discrete : bool
        Whether A is discrete.
    factor : float
        The growth allowed.

    Returns
    -------
    gap : float
        ``log(factor) / rate`` for the fastest growing mode's rate; ``inf`` for a plant
        without one.

    """
    eig = np.linalg.eigvals(np.asarray(A, dtype=float))
    if discrete:
        with np.errstate(divide='ignore'):
            rates = np.log(np.abs(eig)) / dt
    else:
        rates = eig.real
    rate = float(np.max(rates)) if rates.size else 0.0
    return np.inf if rate <= 1e-12 else float(np.log(factor) / rate)


def settling_time(poles, dt, discrete=False):
    """
    Return the time, s, in which the slowest of the poles decays to 2 % (4 time constants).

    Parameters
    ----------
    poles : array_like of complex
        s-plane poles, or z-plane if ``discrete``.
    dt : float
        The sample time, s (for discrete poles).
    discrete : bool
        Whether the poles are discrete.

    Returns
    -------
    t : float
        ``inf`` if a pole does not decay.

    """
    poles = np.asarray(poles, dtype=complex).ravel()
    with np.errstate(divide='ignore'):
        rates = -np.log(np.abs(poles)) / dt if discrete else -poles.real
    slowest = float(np.min(rates)) if rates.size else np.inf
    return np.inf if slowest <= 0.0 else 4.0 / slowest


def pole_margin_problem(poles, A, dt, discrete=False, name='poles'):
    """
    Return why the poles lack a stability margin on the plant's time scale, or None.

    A pole must decay faster than the plant's slowest non-zero mode divided by
    :data:`POLE_SLOWEST` (``-1e-300`` is stable in name only), and not faster than
    :data:`POLE_FASTEST` / dt (a pole the sampling cannot realise, with a huge gain).
    Discrete poles z are compared as ``log(z) / dt``.

    Parameters
    ----------
    poles : array_like of complex
        The poles (s-plane, or z-plane if ``discrete``).
    A : (n, n) array_like
        The plant's state matrix (its eigenvalues set the time scale).
    dt : float
        The sample time, s.
    discrete : bool
        Whether poles and A are discrete.
    name : str
        The parameter named in the report.

    Returns
    -------
    problem : str or None

    """
    poles = np.asarray(poles, dtype=complex).ravel()
    eig = np.linalg.eigvals(np.asarray(A, dtype=float))
    with np.errstate(divide='ignore'):
        s_poles = np.log(poles) / dt if discrete else poles
        s_eig = np.log(eig.astype(complex)) / dt if discrete else eig
    rates = np.abs(s_eig)
    rates = rates[np.isfinite(rates) & (rates > 1e-12)]
    slowest = (rates.min() if rates.size else 1.0 / dt) / POLE_SLOWEST
    fastest = POLE_FASTEST / dt
    for p, s in zip(poles, s_poles):
        shown = f'{p.real:.6g}' if p.imag == 0 else f'{p.real:.6g}{p.imag:+.6g}j'
        if not np.isfinite(s) or -s.real < slowest:
            return (f'{name}: pole {shown} decays slower than {slowest:.3g} 1/s (the '
                    f"plant's slowest mode / {POLE_SLOWEST:g}): no useful stability margin")
        if abs(s) > fastest:
            return (f'{name}: pole {shown} is faster than {fastest:.3g} 1/s '
                    f'({POLE_FASTEST:g} / the sample time {dt:g} s): not realisable')
    return None
