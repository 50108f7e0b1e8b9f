"""A host-sync finder for training steps that works on the CPU: which lines read a tensor's values on the host.

On the GPU each such read (``.item()``, ``bool(t)``, ``t.tolist()``, ``t.cpu()``, a boolean mask index,
``torch.nonzero`` ...) waits for every queued kernel, so a step with a few of them runs at the speed of the host
rather than of the GPU. On the CPU nothing waits, but the same calls are made: :class:`SyncFinder` wraps them in
torch (while it is entered) and counts each call by the project line that made it, per training step, with the
step's kind (:meth:`SyncFinder.watch_trainer`): the ordinary step should make none. On CUDA it can also turn on
``torch.cuda.set_sync_debug_mode("warn")`` and count torch's own sync warnings by line (what the wrapped calls
cannot see: a sync inside an operator). The rasterizer's pair count, read by the compiled extension itself in a
synced binning, is seen by neither (training reads it a render late instead: retinexgs.render.pair_budget).

    python scripts/profiling.py syncs [SCENE] [--device cpu|cuda] [--steps 300] [--profile 100]
"""
from __future__ import annotations

import collections
import contextlib
import os
import sys
import traceback
import warnings
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

import torch

__all__ = ["SyncFinder", "STEP_KINDS"]

# The kinds of a training step, in the order reported. Only "ordinary" steps must make no host read: the others
# read on purpose (loss values for the log, a checkpoint, densification decisions, graph re-captures).
STEP_KINDS = ("ordinary", "first", "check", "density", "after_event", "outside")

# Tensor methods that hand a tensor's values to the host (each one a sync on the GPU).
_READ_METHODS = ("item", "tolist", "cpu", "numpy", "__bool__", "__int__", "__float__", "__index__")
# Operators whose output size depends on the values (the host must read a count before allocating it).
_SIZE_FUNCTIONS = ("nonzero", "argwhere", "unique", "unique_consecutive", "masked_select")

_HERE = os.path.abspath(__file__)
_WARNINGS = os.path.abspath(warnings.__file__)
_TORCH_DIR = os.path.dirname(os.path.abspath(torch.__file__)) + os.sep


def _has_bool_index(index: Any) -> bool:
    """Whether an index (``t[index]``) holds a boolean tensor: a mask, whose selected count the host reads."""
    if isinstance(index, torch.Tensor):
        return index.dtype == torch.bool and index.dim() > 0
    if isinstance(index, (tuple, list)):
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool and i.dim() > 0 for i in index)
    return False


def _to_host(args: tuple, kwargs: dict) -> bool:
    """Whether ``Tensor.to(*args, **kwargs)`` names the CPU as its device."""
    for a in list(args[:1]) + [kwargs.get("device")]:
        if isinstance(a, (str, torch.device)) and torch.device(a).type == "cpu":
            return True
    return False


def _sizes_output(*args, **kwargs) -> bool:
    """Whether ``repeat_interleave(*args, **kwargs)`` must read its repeats on the host to size its output: a
    tensor of repeats (or the one-argument form) without ``output_size``."""
    if kwargs.get("output_size") is not None or len(args) >= 4:
        return False
    repeats = args[1] if len(args) > 1 else kwargs.get("repeats", args[0] if args else None)
    return isinstance(repeats, torch.Tensor)


class SyncFinder:
    """Counts host reads of tensor values by call site while entered (``with SyncFinder() as f: ...``).

    A call site is the innermost frame outside torch and this module (``file:line (function)``, the path relative
    to the current directory), followed by ``via torch/...`` when torch's own Python code made the read (e.g.
    ``via torch/optim/adam.py``: the CPU's Adam reads its step count; the trainer's on CUDA, train/adam.py, does not).
    A read made inside another counted read (``repr`` of a tensor calling ``.item()``) counts once.

    ``cuda_warn``: also run with ``torch.cuda.set_sync_debug_mode("warn")`` and count torch's sync warnings
    by site, under the name ``cuda-sync``. ``ignore_via``: reads made through these torch folders are counted
    apart (:attr:`ignored`), in no step: by default the CPU's Adam's (``torch/optim/``), which the trainer's
    Adam on CUDA (train/adam.py: host step counts) does not make. ``cuda_profile``: also count the CUDA runtime's
    synchronize calls of each step (torch.profiler), whoever made them (the extension's binning included), under the
    name ``cuda-runtime`` with the runtime call's name as the site."""

    def __init__(self, cuda_warn: bool = False, ignore_via: Tuple[str, ...] = ("torch/optim/",),
                 cuda_profile: bool = False) -> None:
        self.cuda_warn = cuda_warn and torch.cuda.is_available()
        self.cuda_profile = cuda_profile and torch.cuda.is_available()
        self._range: Any = None
        self._prof: Any = None
        self.ignore_via = ignore_via
        self.ignored: collections.Counter = collections.Counter()  # (what, site) read through ignore_via
        # step -> (its kind, Counter of (what, site)): see begin_step / set_kind.
        self.steps: Dict[int, Tuple[str, collections.Counter]] = {}
        self.outside: collections.Counter = collections.Counter()  # reads made outside any marked step
        self._step: Optional[int] = None
        self._depth = 0
        self._saved: List[Tuple[Any, str, Any, bool]] = []
        self._stack = contextlib.ExitStack()

    # ---- steps ---------------------------------------------------------------------------------------------
    def begin_step(self, step: int, kind: str = "ordinary") -> None:
        """Reads from now on belong to ``step`` (of ``kind``, one of :data:`STEP_KINDS`; settable later)."""
        self._step = step
        self.steps[step] = (kind, collections.Counter())
        if self._prof is not None:  # the step as a profiler range: the runtime's syncs are matched to it by time
            self._close_range()
            self._range = torch.autograd.profiler.record_function(f"syncfinder/step/{step}")
            self._range.__enter__()

    def _close_range(self) -> None:
        if self._range is not None:
            self._range.__exit__(None, None, None)
            self._range = None

    def _count_runtime_syncs(self) -> None:
        """The profiled CUDA runtime synchronize calls, each added to the step whose range holds it."""
        events = list(self._prof.events())
        spans = sorted((e.time_range.start, e.time_range.end, int(e.name.rsplit("/", 1)[1])) for e in events
                       if e.name.startswith("syncfinder/step/"))
        for e in events:
            if "Synchronize" not in e.name or e.name.startswith("syncfinder/"):
                continue
            t = e.time_range.start
            step = next((s for a, b, s in spans if a <= t <= b), None)
            counts = self.steps[step][1] if step in self.steps else self.outside
            counts[("cuda-runtime", e.name)] += 1

    def set_kind(self, kind: str) -> None:
        """The current step's kind, once it is known (e.g. when the step's check flag is)."""
        if self._step is not None:
            self.steps[self._step] = (kind, self.steps[self._step][1])

    def watch_trainer(self, trainer) -> Callable[[], None]:
        """Mark ``trainer``'s steps (a :class:`retinexgs.train.trainer.Trainer`): a step begins where its loop
        draws the step's views and its kind is set when ``train_step`` starts: ``first`` (the session's first
        step: graph captures, warm-up), ``check`` (a logging or checkpoint step: reads the loss values),
        ``density`` (a densification, pruning or opacity reset), ``after_event`` (the step after a density event:
        the CUDA graphs are captured again) or ``ordinary``. Returns a function that removes the marks."""
        batch_indices, train_step = trainer._batch_indices, trainer.train_step
        state = {"first": True, "event": False}

        def marked_batch_indices():
            self.begin_step(trainer.step + 1)
            return batch_indices()

        def marked_train_step(step, tv, *args, **kwargs):
            check = kwargs.get("check", args[0] if args else True)
            if state["first"]:
                kind = "first"
            elif trainer.strategy.edits_at(step):
                kind = "density"
            elif check:
                kind = "check"
            elif state["event"]:
                kind = "after_event"
            else:
                kind = "ordinary"
            self.set_kind(kind)
            values = train_step(step, tv, *args, **kwargs)
            state["first"], state["event"] = False, bool(values.get("event"))
            return values

        trainer._batch_indices, trainer.train_step = marked_batch_indices, marked_train_step

        def unwatch() -> None:
            del trainer._batch_indices, trainer.train_step  # the class's methods again

        return unwatch

    # ---- counts --------------------------------------------------------------------------------------------
    def by_kind(self) -> Dict[str, Tuple[int, collections.Counter]]:
        """kind -> (number of steps of that kind, Counter of (what, site) over them); ``outside``: reads
        before the first marked step."""
        out: Dict[str, Tuple[int, collections.Counter]] = {}
        for kind, counts in self.steps.values():
            n, total = out.get(kind, (0, collections.Counter()))
            out[kind] = (n + 1, total + counts if counts else total)
        if self.outside:
            out["outside"] = (0, self.outside)
        return out

    def ordinary(self) -> collections.Counter:
        """Every read the ordinary steps made, by (what, site)."""
        return self.by_kind().get("ordinary", (0, collections.Counter()))[1]

    def report(self, out=None) -> None:
        """Print the reads per step of each kind, by site, most frequent first."""
        out = out or sys.stdout
        kinds = self.by_kind()
        for kind in STEP_KINDS:
            if kind not in kinds:
                continue
            n, counts = kinds[kind]
            total = sum(counts.values())
            per = f"{total / n:.2f} per step over {n} steps" if n else f"{total} in all"
            print(f"{kind}: {per}", file=out)
            for (what, site), c in counts.most_common():
                print(f"  {c / n if n else c:8.2f}  {what:18s} {site}", file=out)
        if self.ignored:
            print(f"ignored (through {', '.join(self.ignore_via)}), in all:", file=out)
            for (what, site), c in self.ignored.most_common():
                print(f"  {c:8d}  {what:18s} {site}", file=out)

    def _record(self, what: str) -> None:
        site = self._site()
        if any(f"via {v}" in site for v in self.ignore_via):
            self.ignored[(what, site)] += 1
            return
        counts = self.steps[self._step][1] if self._step is not None else self.outside
        counts[(what, site)] += 1

    @staticmethod
    def _site() -> str:
        via = None
        for frame in reversed(traceback.extract_stack()):
            path = os.path.abspath(frame.filename)
            if path in (_HERE, _WARNINGS):  # the finder itself; the warnings machinery (cuda_warn)
                continue
            if path.startswith(_TORCH_DIR) or "/torch/" in path.replace(os.sep, "/"):
                via = "torch/" + os.path.relpath(path, _TORCH_DIR).replace(os.sep, "/")
                continue
            rel = os.path.relpath(path) if path.startswith(os.getcwd()) else path
            return f"{rel}:{frame.lineno} ({frame.name})" + (f" via {via}" if via else "")
        return "?" + (f" via {via}" if via else "")

    # ---- patching ------------------------------------------------------------------------------------------
    def _wrap(self, owner: Any, name: str, what: str, when: Optional[Callable[..., bool]] = None) -> None:
        original = getattr(owner, name)
        own = name in vars(owner)
        finder = self

        def counted(*args, **kwargs):
            if finder._depth == 0 and (when is None or when(*args, **kwargs)):
                finder._record(what)
            finder._depth += 1
            try:
                return original(*args, **kwargs)
            finally:
                finder._depth -= 1

        counted.__name__ = getattr(original, "__name__", name)
        setattr(owner, name, counted)
        self._saved.append((owner, name, original, own))

    def __enter__(self) -> "SyncFinder":
        T = torch.Tensor
        for name in _READ_METHODS:
            self._wrap(T, name, f".{name.strip('_')}()" if not name.startswith("__") else f"{name[2:-2]}(tensor)")
        self._wrap(T, "to", ".to(cpu)", lambda self_, *a, **k: _to_host(a, k))
        for name in _SIZE_FUNCTIONS:
            for owner in (torch, T):
                if hasattr(owner, name):
                    self._wrap(owner, name, f"{name}")
        # torch.where(cond) with one argument is nonzero; repeat_interleave without output_size counts its output.
        self._wrap(torch, "where", "where(cond)", lambda *a, **k: len(a) + len(k) == 1)
        for owner in (torch, T):
            self._wrap(owner, "repeat_interleave", "repeat_interleave", _sizes_output)
        self._wrap(T, "__getitem__", "mask index", lambda self_, index: _has_bool_index(index))
        self._wrap(T, "__setitem__", "mask assign", lambda self_, index, value: _has_bool_index(index))
        if self.cuda_warn:
            self._stack.enter_context(self._cuda_warnings())
        if self.cuda_profile:
            acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
            self._prof = self._stack.enter_context(torch.profiler.profile(activities=acts))
        return self

    def __exit__(self, *exc) -> None:
        self._close_range()
        self._step = None  # what follows (the profiler's closing sync) belongs to no step
        if self._prof is not None:
            torch.cuda.synchronize()
        self._stack.close()
        if self._prof is not None:
            self._count_runtime_syncs()
            self._prof = None
        while self._saved:
            owner, name, original, own = self._saved.pop()
            if own:
                setattr(owner, name, original)
            else:
                delattr(owner, name)

    @contextlib.contextmanager
    def _cuda_warnings(self) -> Iterator[None]:
        """torch's sync debug mode ("warn"), each warning counted by the line that caused it."""
        finder = self

        def show(message, category, filename, lineno, file=None, line=None):
            if "synchronizing" in str(message):
                finder._record("cuda-sync")
            else:
                shown(message, category, filename, lineno, file, line)

        with warnings.catch_warnings():
            warnings.simplefilter("always")
            shown, warnings.showwarning = warnings.showwarning, show
            torch.cuda.synchronize()
            torch.cuda.set_sync_debug_mode("warn")
            try:
                yield
            finally:
                torch.cuda.set_sync_debug_mode("default")
                warnings.showwarning = shown
