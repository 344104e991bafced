"""The one time loop: step an integrator and hand every step to sinks.

:func:`run_loop` steps any :class:`~dolfinx_lopinf.fem.integrators.Integrator` (midpoint, linear
or Newton, and Newmark) and hands each step to its sinks, which record what a scene needs:
states (:class:`~dolfinx_lopinf.fem.fom.StateRecorder`,
:meth:`~dolfinx_lopinf.fem.recorder.SnapshotRecorder.sink`), outputs (:class:`OutputProbe`),
energies (:class:`EnergyProbe`), streaming POD (:class:`Every`, e.g.
:meth:`~dolfinx_lopinf.fem.streaming.StreamingPOD.sink`), fields (:class:`FieldSnapshots`),
checkpoints (:class:`~dolfinx_lopinf.fem.checkpoint.CheckpointSink`) and a progress bar
(:class:`Progress`). A sink sees a :class:`LoopState`: the step number, the integrator, and the
velocity and energy at this step, each computed once and shared.
"""

from __future__ import annotations

import time

from ._dolfinx import MPI, dolfinx
from ..core._checks import check_int
from ..errors import InputError
from .agreement import agree, together
from .integrators import MidpointIntegrator


from .newmark import NewmarkIntegrator


class LoopState:
    """What a sink sees at step ``k`` of :func:`run_loop`: the integrator, the step number,
    and the velocity and energy at this step (each computed once, on first request, and
    shared by every sink)."""

    def __init__(self, integrator, n_steps: int, comm):
        self.integrator, self.n_steps, self.comm = integrator, int(n_steps), comm
        self.k = 0
        self.t_loop_start = time.perf_counter()
        self._v = None
        self._v_step = self._e_step = -1
        self._e = None

    @property
    def t(self) -> float:
        return self.integrator.t

    @property
    def q(self):
        return self.integrator.q

    def velocity(self):
        """The velocity at this step (a Function owned by the loop state; do not keep it)."""
        if self._v_step != self.k:
            if self._v is None:
                self._v = dolfinx.fem.Function(self.integrator.q.function_space)
            self.integrator.velocity(self._v)
            self._v_step = self.k
        return self._v

    def energy(self) -> float:
        """The integrator's energy at this step (collective)."""
        if self._e_step != self.k:
            self._e = self.integrator.energy(self.velocity())
            self._e_step = self.k
        return self._e


class Sink:
    """A sink of the time loop: :meth:`start` at step 0 (the initial state), :meth:`after`
    after every step, :meth:`finish` once the loop ends. Override what you need; by default
    :meth:`start` does what :meth:`after` does."""

    def start(self, s: LoopState) -> None:
        self.after(s)

    def after(self, s: LoopState) -> None:
        pass

    def finish(self, s: LoopState) -> None:
        pass


class Every(Sink):
    """Call ``fn(state)`` at every ``every``-th step k (k = 0 included) up to ``until_step``,
    or exactly at ``steps`` when given."""

    def __init__(self, fn, *, every: int = 1, until_step: int | None = None, steps=None):
        self.fn, self.every, self.until_step = fn, check_int(every, "every", 1), until_step
        self.steps = None if steps is None else set(int(k) for k in steps)

    def after(self, s):
        if self.steps is not None:
            if s.k in self.steps:
                self.fn(s)
        elif s.k % self.every == 0 and (self.until_step is None or s.k <= self.until_step):
            self.fn(s)


class OutputProbe(Sink):
    """y = sum over ranks of E q_local every ``every`` steps (``values``: list of (p,) arrays,
    ``times``: their times)."""

    def __init__(self, output_matrix, *, every: int = 1):
        self.E, self.every = output_matrix, every
        self.values, self.times = [], []

    def after(self, s):
        if s.k % self.every == 0:
            self.values.append(s.comm.allreduce(self.E @ s.q.x.array))
            self.times.append(s.t)


class EnergyProbe(Sink):
    """The integrator's energy every ``every`` steps (``values``, ``times``)."""

    def __init__(self, *, every: int = 1):
        self.every = every
        self.values, self.times = [], []

    def after(self, s):
        if s.k % self.every == 0:
            self.values.append(s.energy())
            self.times.append(s.t)


class FieldSnapshots(Sink):
    """Copies of the local dof array (owned + ghosts) at the given steps: ``fields[k]``."""

    def __init__(self, steps):
        self.steps = set(int(k) for k in steps)
        self.fields = {}

    def after(self, s):
        if s.k in self.steps:
            self.fields[s.k] = s.q.x.array.copy()


class Progress(Sink):
    """A tqdm bar on rank 0 (updated every ``every`` steps)."""

    def __init__(self, *, every: int = 1000, desc: str = "FOM"):
        self.every, self.desc, self.bar, self._shown = every, desc, None, 0

    def _open(self, s):
        if self.bar is None and s.comm.rank == 0:
            from tqdm.auto import tqdm
            self.bar = tqdm(total=s.n_steps, desc=self.desc, unit="step", mininterval=0.5,
                            leave=False)
            if s.k:
                self.bar.update(s.k)
                self._shown = s.k

    def start(self, s):
        self._open(s)

    def after(self, s):
        self._open(s)
        if self.bar is not None and s.k % self.every == 0:
            self.bar.update(s.k - self._shown)
            self._shown = s.k

    def finish(self, s):
        if self.bar is not None:
            self.bar.close()


def run_loop(integrator, n_steps: int, sinks=(), *, inputs=None, first_step: int = 1) -> dict:
    """The time loop: ``n_steps`` steps of ``integrator`` (any
    :class:`~dolfinx_lopinf.fem.integrators.Integrator`, already initialised), each handed to the
    ``sinks`` in order.

    Args:
        integrator: midpoint (linear or Newton) or Newmark integrator, initialised.
        n_steps: steps to take.
        sinks: :class:`Sink` objects (``StateRecorder``, ``OutputProbe``, ``EnergyProbe``,
            ``Every`` - e.g. ``StreamingPOD.sink()`` -, ``FieldSnapshots``,
            ``CheckpointSink``, ``Progress``), or plain callables ``f(state)`` called at
            every step including step 0.
        inputs: ``inputs(t) -> values`` at the new time t_k = t_0 + k dt, passed to
            ``integrator.step`` (schemes with input channels, e.g. Newmark); None: no inputs.
        first_step: 1 for a fresh run (the sinks' ``start`` sees step 0); k > 1 to continue
            a run restored to step k - 1 (``start`` is skipped).

    Returns:
        ``{"seconds": wall time of the loop (max over ranks), "steps": n_steps}``.

    Collective: the arguments are checked on every rank and agreed on (n_steps, first_step,
    the kinds of sinks, whether there are inputs, the integrator's dt and t must be the same
    on every rank; the same error on every rank otherwise), the integrator must be open and
    initialised. With inputs, their values are compared at every step (one small allgather;
    on one rank nothing). A sink or input function that raises on one rank only aborts the
    job (the other ranks are inside the next step's solve; see
    :mod:`dolfinx_lopinf.fem.agreement`).
    """
    for name in ("step", "velocity", "energy", "dt", "q"):
        if not hasattr(integrator, name):
            raise InputError(f"run needs an Integrator (midpoint or Newmark, see "
                             f"dolfinx_lopinf.fem.integrators) or a LagrangianSystem, got "
                             f"{type(integrator).__name__} (no '{name}')")
    comm = integrator.q.function_space.mesh.comm
    loop, problem = None, None
    try:
        loop = _loop_plan(integrator, n_steps, sinks, inputs, first_step)
    except Exception as exc:  # noqa: BLE001 - every rank must hear of it
        problem = exc
    agree(comm, "run", problem, **({} if loop is None else loop.pop("settings")))
    n_steps, first_step, sinks = loop["n_steps"], loop["first_step"], loop["sinks"]
    state = LoopState(integrator, n_steps, comm)
    dt = integrator.dt
    t_begin = integrator.t - (first_step - 1) * dt
    state.k = first_step - 1
    if loop["agreed"]:
        integrator._agreed_loop = True  # every rank steps without values: no per-step check
    try:
        with together(comm, "run (the time loop: steps, inputs and sinks)"):
            if first_step == 1:
                for sink in sinks:
                    sink.start(state)
            for k in range(first_step, n_steps + 1):
                if inputs is None:
                    integrator.step()
                else:
                    integrator.step(inputs(t_begin + k * dt))
                state.k = k
                for sink in sinks:
                    sink.after(state)
    finally:
        if loop["agreed"]:
            integrator._agreed_loop = False
    seconds = comm.allreduce(time.perf_counter() - state.t_loop_start, op=MPI.MAX)
    with together(comm, "run (the sinks' finish)"):
        for sink in sinks:
            sink.finish(state)
    return {"seconds": seconds, "steps": n_steps}


def _loop_plan(integrator, n_steps, sinks, inputs, first_step) -> dict:
    """:func:`run_loop`'s checks on this rank alone (raises; no collective): the counts, the
    sinks as :class:`Sink` objects, the step function to call, the settings every rank must
    share."""
    n_steps = check_int(n_steps, "n_steps", 0)
    first_step = check_int(first_step, "first_step", 1)
    if isinstance(sinks, (Sink, str, bytes)) or callable(sinks) or not hasattr(sinks, "__iter__"):
        raise InputError(f"sinks must be a list of Sink objects or callables f(state), got "
                         f"{type(sinks).__name__}; wrap a single sink in a list: sinks=[sink]")
    sinks = list(sinks)
    for i, s in enumerate(sinks):
        if not isinstance(s, Sink) and not callable(s):
            raise InputError(f"sinks[{i}] = {s!r} is neither a Sink (StateRecorder, OutputProbe, "
                             "EnergyProbe, FieldSnapshots, Every, ...) nor a callable f(state) "
                             "called at every step; pass one of those")
    sinks = [s if isinstance(s, Sink) else Every(s) for s in sinks]
    if inputs is not None and not callable(inputs):
        raise InputError(f"inputs must be a callable inputs(t) -> input values (or None), got "
                         f"{type(inputs).__name__}")
    name = type(integrator).__name__
    if getattr(integrator, "closed", False):
        raise InputError(f"the {name} was closed (close() or the end of its with block) and its "
                         "PETSc objects destroyed; make a new one")
    if not getattr(integrator, "initialized", True):
        raise InputError(f"the {name} was never initialised: it would step from zero and "
                         "record zeros. Call integrator.initialize(...) before run(integrator, "
                         "n_steps) (run(system, q0, v0, dt, t_end) does it for you)")
    agreed = False  # True: the integrator's step need not agree on its arguments every step
    if isinstance(integrator, MidpointIntegrator):
        if inputs is not None:
            raise InputError("a MidpointIntegrator takes no input values (inputs= is for "
                             "schemes with input channels, e.g. Newmark): put the forcing into "
                             "the LagrangianSystem (forcing=..., time=...)")
        agreed = True
    elif isinstance(integrator, NewmarkIntegrator):
        if integrator.inputs and inputs is None:
            raise InputError(f"this NewmarkIntegrator has {len(integrator.inputs)} input "
                             "channel(s): pass inputs=lambda t: values")
        if not integrator.inputs and inputs is not None:
            raise InputError("this NewmarkIntegrator has no input forms: drop inputs= (or build "
                             "it with input_forms=...)")
        agreed = inputs is None  # with inputs, their values are compared at every step
    # a progress bar on rank 0 only is fine (no collective); every other sink must be on all
    settings = {"n_steps": n_steps, "first_step": first_step,
                "sinks": [type(s).__name__ for s in sinks if not isinstance(s, Progress)],
                "inputs": inputs is not None,
                "integrator": name, "dt": float(integrator.dt), "t": float(integrator.t)}
    return {"n_steps": n_steps, "first_step": first_step, "sinks": sinks, "agreed": agreed,
            "settings": settings}
