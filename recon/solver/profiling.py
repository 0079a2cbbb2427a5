"""Profile of the solver's iterations by phase (:class:`PhaseTimer`)."""
from __future__ import annotations

def _no_timer(phase, *arrays, iteration_end=False):
    pass


class PhaseTimer:
    """Profile of the solver's iterations by phase (``fit(..., timer=PhaseTimer())``).

    The loop calls ``timer(phase, *arrays)`` after each phase ('sampling': pings, bins,
    sample points and targets; 'forward': the forward model; 'loss': data term and priors;
    'backward': AD to the parameters; 'adam': the optimiser step; 'host': reading the loss
    values, history, callback). The timer evaluates the phase's arrays, waits for the device
    and charges the wall time since the previous call to the phase, with the Dr.Jit kernels
    launched meanwhile (their count, execution time and how many were compiled, i.e. missed
    the in-memory kernel cache). Forcing evaluation at phase ends changes kernel fusion a
    little: the profiled iteration is slightly slower than a free-running one.

    ``rows()`` → per phase (name, wall seconds, kernel seconds, kernel launches, compiled
    kernels, process CPU seconds — each per iteration) over the iterations after ``skip``.
    On a shared machine the CPU seconds of a one-thread run are the steadier figure.
    """

    PHASES = ("sampling", "forward", "loss", "backward", "adam", "host")

    def __init__(self, skip: int = 2):
        import time
        import drjit as dr
        self._clock, self._cpu = time.perf_counter, time.process_time
        self.skip, self.iteration = int(skip), 0
        self.totals = {}
        self._last = self._last_cpu = None
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()                      # drop what ran before

    def __call__(self, phase, *arrays, iteration_end=False):
        import drjit as dr
        dr.eval(*(a for a in arrays if a is not None))
        dr.sync_thread()
        now, cpu = self._clock(), self._cpu()
        hist = dr.kernel_history()
        if self._last is not None and phase != "setup" and self.iteration >= self.skip:
            t = self.totals.setdefault(phase, [0.0, 0.0, 0, 0, 0.0])
            t[0] += now - self._last
            t[4] += cpu - self._last_cpu
            for k in hist:
                t[1] += float(k.get("execution_time", 0.0)) * 1e-3
                if k["type"] == dr.KernelType.JIT:
                    t[2] += 1
                    t[3] += 0 if k.get("cache_hit") else 1
        self._last, self._last_cpu = now, cpu
        if iteration_end:
            self.iteration += 1

    def close(self):
        import drjit as dr
        dr.set_flag(dr.JitFlag.KernelHistory, False)

    def rows(self):
        n = max(self.iteration - self.skip, 1)
        return [(p, *(v / n for v in self.totals[p])) for p in self.PHASES if p in self.totals]
