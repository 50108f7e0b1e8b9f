"""Training on several GPUs (or CPU processes) through torch.distributed: data parallel over views (issue 34).

Launched by ``torchrun --nproc_per_node N -m retinexgs train ...`` or ``retinexgs train --gpus N`` (which
re-launches itself through ``torch.distributed.run``; :func:`relaunch`). Every rank holds the whole model (the
Gaussians, the illumination MLP, the EnhancementNet) and its Adam state; a step trains B = ranks ×
``train.views_per_rank`` views, each rank rendering its own and back-propagating them, then one all-reduce sums
the gradients (the trainer divides by B: the mean over the batch's views) before the optimiser step. What else
crosses ranks, and when (docs/architecture.md, "Several GPUs"):

- set-up: rank 0 reads the scene first (it fills the scene's caches), then the others; the decomposition is
  computed in shards (views ``i % N == rank``) and read back by every rank; rank 0's model state is broadcast
  (``illum_ref`` and the mean background are computed from every view);
- each step: the gradients (one flat buffer per dtype); on logging steps the loss values (the batch's mean);
- before a densification: the density statistics (sums of the 2D-gradient norms and visibility counts, maxima
  of the screen radii and of the image size); after any density event (densify, prune, opacity reset) rank 0's
  Gaussians and their Adam moments are broadcast, after every rank compared its own with rank 0's;
- at the end: per-rank statistics and a fingerprint of the parameters (gathered by rank 0), the evaluation's
  per-view rows (each rank renders its share of the test views).

Only rank 0 writes (checkpoints, logs, metrics.json) and prints. A world of one rank never initialises a process
group: it is the plain run. Collectives time out after ``RETINEXGS_DIST_TIMEOUT`` seconds (default 600; set-up
barriers, which wait for one rank's scene reading or its share of the decomposition, after
``RETINEXGS_DIST_SETUP_TIMEOUT``, default 4 h), and a failed or timed-out collective becomes a
:class:`RankFailure` that names the rank and what it was waiting for. The NCCL collectives run in eager code,
never inside the CUDA graphs the trainer captures; a capture that fails for any reason (NCCL's watchdog thread
querying its events during a capture was a known torch issue, handled in recent torch) is logged by the trainer
and that part runs eagerly.
"""
from __future__ import annotations

import datetime
import math
import os
import resource
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import torch
import torch.distributed as dist
from torch import Tensor, nn

from retinexgs.errors import UserError
from retinexgs.model.gaussians import PARAM_NAMES
from retinexgs.retinex.cache import decompose_images, scene_cache_root
from retinexgs.config.schema import Config
from retinexgs.strategy.ops import resize_gaussians

TIMEOUT_ENV = "RETINEXGS_DIST_TIMEOUT"
SETUP_TIMEOUT_ENV = "RETINEXGS_DIST_SETUP_TIMEOUT"
DEFAULT_TIMEOUT = 600.0
DEFAULT_SETUP_TIMEOUT = 4 * 3600.0
# Used only by the tests: the rank RETINEXGS_TEST_FAULT_RANK (default 1) exits (os._exit) or hangs at that step.
TEST_DIE_ENV = "RETINEXGS_TEST_DIE_AT_STEP"
TEST_HANG_ENV = "RETINEXGS_TEST_HANG_AT_STEP"
TEST_FAULT_RANK_ENV = "RETINEXGS_TEST_FAULT_RANK"

LR_BATCH_SCALING = ("sqrt", "linear", "none")


class RankFailure(UserError):
    """A collective failed or timed out: another rank stopped, crashed or is stuck."""


def lr_batch_factor(mode: str, batch: int) -> float:
    """The factor every learning rate is multiplied by for a step of ``batch`` views (``train.lr_batch_scaling``):
    sqrt(B) (Grendel-GS, gsplat), B, or 1. Exactly 1 for B = 1."""
    if mode not in LR_BATCH_SCALING:
        raise ValueError(f"train.lr_batch_scaling must be one of {', '.join(LR_BATCH_SCALING)}, got {mode!r}")
    if batch == 1 or mode == "none":
        return 1.0
    return math.sqrt(batch) if mode == "sqrt" else float(batch)


MOMENTUM_BATCH_SCALING = ("power", "none")
ADAM_BETAS = (0.9, 0.999)  # torch's defaults, the betas of a batch of one view


def adam_betas_for_batch(mode: str, batch: int) -> Tuple[float, float]:
    """Adam's (β1, β2) for a step of ``batch`` views (``train.momentum_batch_scaling``). ``power``: β^B, so that
    the moments forget at the same rate per view seen as in a run of one view a step (B steps of β decay by β^B;
    Grendel-GS's momentum rule); ``none``: torch's defaults. Exactly the defaults for B = 1."""
    if mode not in MOMENTUM_BATCH_SCALING:
        raise ValueError(f"train.momentum_batch_scaling must be one of {', '.join(MOMENTUM_BATCH_SCALING)}, "
                         f"got {mode!r}")
    if batch == 1 or mode == "none":
        return ADAM_BETAS
    return (ADAM_BETAS[0] ** batch, ADAM_BETAS[1] ** batch)


def _env_seconds(name: str, default: float) -> float:
    raw = os.environ.get(name)
    if raw in (None, ""):
        return default
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not value > 0:
        raise UserError(f"{name}={raw!r}: expected a number of seconds > 0")
    return value


def _env_int(name: str) -> Optional[int]:
    raw = os.environ.get(name)
    if raw in (None, ""):
        return None
    try:
        return int(raw)
    except ValueError:
        raise UserError(f"{name}={raw!r}: expected an integer (torchrun sets it)") from None


def process_start_time() -> float:
    """When this process started (wall clock; Linux: from /proc, 10 ms resolution), or now where unknown."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        ticks = int(fields[19])  # field 22 of stat(5), "starttime", in clock ticks since boot
        since_boot = time.clock_gettime(time.CLOCK_BOOTTIME)
        return time.time() - (since_boot - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return time.time()


def max_rss_gb() -> float:
    """This process's peak resident memory (getrusage; KiB on Linux) in GiB."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 2**20 if sys.platform != "darwin" else kib / 2**30


@dataclass
class Distributed:
    """This process's place among the ranks; a default instance is the plain single-process run, whose
    collectives are no-ops (none is ever called with one rank)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    backend: Optional[str] = None
    device: torch.device = torch.device("cpu")
    timeout: float = DEFAULT_TIMEOUT
    setup_timeout: float = DEFAULT_SETUP_TIMEOUT
    _host: Any = None  # a gloo group for Python objects and barriers (the set-up timeout)
    _fault: Optional[Tuple[str, int, int]] = None  # tests: (die|hang, step, rank)

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def describe(self) -> str:
        return f"rank {self.rank} of {self.world}"

    # ---- errors ------------------------------------------------------------------------------------------
    @contextmanager
    def _collective(self, what: str, setup: bool = False) -> Iterator[None]:
        """Turn a failed or timed-out collective into a RankFailure naming this rank and what it waited for."""
        try:
            yield
        except RuntimeError as exc:  # DistBackendError, DistNetworkError, gloo's and NCCL's errors
            detail = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:300]
            limit, env = (self.setup_timeout, SETUP_TIMEOUT_ENV) if setup else (self.timeout, TIMEOUT_ENV)
            timed_out = "timed out" in str(exc).lower() or "timeout" in str(exc).lower()
            why = (f"no answer within {limit:.0f} s ({env})" if timed_out else
                   "another rank stopped or is unreachable")
            raise RankFailure(f"{self.describe()}: {what} failed: {why} ({type(exc).__name__}: {detail}). A rank "
                              f"that failed prints its own error; torchrun reports which one. The run folder's "
                              "last checkpoint is intact (resume with any number of ranks).") from exc

    # ---- collectives -------------------------------------------------------------------------------------
    def barrier(self, what: str) -> None:
        """Wait for every rank (on the host group: the set-up timeout)."""
        if not self.enabled:
            return
        with self._collective(f"waiting for {what}", setup=True):
            dist.barrier(group=self._host)

    def gather_objects(self, obj: Any, what: str) -> List[Any]:
        """Every rank's ``obj`` (picklable), in rank order, on every rank."""
        if not self.enabled:
            return [obj]
        out: List[Any] = [None] * self.world
        with self._collective(f"gathering {what}", setup=True):
            dist.all_gather_object(out, obj, group=self._host)
        return out

    def broadcast_object(self, obj: Any, what: str) -> Any:
        """Rank 0's ``obj`` on every rank."""
        if not self.enabled:
            return obj
        box = [obj if self.is_main else None]
        with self._collective(f"receiving {what} from rank 0"):
            dist.broadcast_object_list(box, src=0, group=self._host)
        return box[0]

    def check_shared_folder(self, folder: Path, what: str) -> None:
        """UserError on every rank unless every rank sees the file rank 0 writes into ``folder``. Ranks on several
        machines (torchrun --nnodes) hand each other data through the file system: the decomposition's shards and
        the view store in the cache folder, checkpoints in the run folder; on a disk of one machine only, the
        others would wait or read another copy. A folder rank 0 cannot write (a read-only scene whose caches are
        complete) is not checked: nobody writes there."""
        if not self.enabled:
            return
        import socket
        import uuid

        host = socket.gethostname()
        token = None
        if self.is_main:
            name = f".rank0-{uuid.uuid4().hex[:12]}"
            try:
                folder.mkdir(parents=True, exist_ok=True)
                (folder / name).write_text(host)
                token = name
            except OSError:
                token = None
        token = self.broadcast_object(token, f"the name of rank 0's probe file in {what}")
        if token is None:
            return
        seen = (folder / token).is_file()
        rows = self.gather_objects((seen, host), f"whether every rank sees {what}")
        self.barrier(f"every rank's look at {what}")
        if self.is_main:
            (folder / token).unlink(missing_ok=True)
        message = shared_folder_problem(folder, what, rows)
        if message:
            raise UserError(message)

    def _flat_groups(self, tensors: Sequence[Tensor]) -> Dict[torch.dtype, List[int]]:
        groups: Dict[torch.dtype, List[int]] = {}
        for i, t in enumerate(tensors):
            groups.setdefault(t.dtype, []).append(i)
        return groups

    def broadcast_(self, tensors: Sequence[Tensor], what: str) -> None:
        """Overwrite ``tensors`` in place with rank 0's (one broadcast per dtype, through a flat buffer on this
        rank's device; the shapes must agree)."""
        if not self.enabled or not tensors:
            return
        for idx in self._flat_groups(tensors).values():
            parts = [tensors[i] for i in idx]
            flat = torch.cat([t.detach().reshape(-1).to(self.device) for t in parts])
            with self._collective(f"receiving {what} from rank 0"):
                dist.broadcast(flat, src=0)
            with torch.no_grad():
                for t, chunk in zip(parts, flat.split([t.numel() for t in parts])):
                    t.copy_(chunk.view_as(t))

    def all_reduce_(self, tensor: Tensor, what: str, op: Any = None) -> Tensor:
        """In-place all-reduce (SUM by default) of one tensor on this rank's device."""
        if self.enabled:
            with self._collective(what):
                dist.all_reduce(tensor, op=dist.ReduceOp.SUM if op is None else op)
        return tensor

    # ---- the step's collectives ----------------------------------------------------------------------------
    def reduce_gradients(self, params: Sequence[Tensor], batch: int, step: int, verify: bool = False) -> None:
        """The batch's mean gradient in every ``p.grad``: this rank's gradients (summed over its views) summed
        over the ranks, one all-reduce per dtype through a flat buffer (the gradients become views of it), and
        divided by ``batch``. A parameter without a gradient here contributes zeros and keeps none; ``verify``
        (a check step: it reads a flag per parameter back) raises when the ranks disagreed on which parameters
        had one. One rank: only the division (none at all for a batch of one)."""
        if not self.enabled:
            if batch > 1:
                grads = [p.grad for p in params if p.grad is not None]
                if grads:
                    torch._foreach_mul_(grads, 1.0 / batch)
            return
        for idx in self._flat_groups(params).values():
            ps = [params[i] for i in idx]
            sizes = [p.numel() for p in ps]
            total = sum(sizes)
            flat = torch.zeros(total + len(ps), dtype=ps[0].dtype, device=self.device)
            chunks = flat[:total].split(sizes)
            present = [p.grad is not None for p in ps]
            with torch.no_grad():
                for p, chunk, has in zip(ps, chunks, present):
                    if has:
                        chunk.copy_(p.grad.reshape(-1))
                flat[total:].copy_(self._flags(present, flat.dtype))
            with self._collective(f"the gradient all-reduce of step {step}"):
                dist.all_reduce(flat)
            if batch > 1:
                flat[:total].mul_(1.0 / batch)
            for p, chunk, has in zip(ps, chunks, present):
                if has:
                    p.grad = chunk.view_as(p)
            if verify:
                flags = flat[total:].tolist()
                if any(f not in (0.0, float(self.world)) or (f > 0) != has for f, has in zip(flags, present)):
                    raise RankFailure(f"{self.describe()}: at step {step} the ranks computed gradients for different "
                                      "parameters (a bug: the ranks' models have diverged)")

    def _flags(self, present: List[bool], dtype: torch.dtype) -> Tensor:
        """[len(present)] 1/0 on the device, built once per pattern (not a host->device copy every step)."""
        cache = self.__dict__.setdefault("_flag_cache", {})
        key = (tuple(present), dtype)
        if key not in cache:
            cache[key] = torch.tensor(present, dtype=dtype).to(self.device)
        return cache[key]

    def mean_values(self, values: Dict[str, float], step: int) -> Dict[str, float]:
        """The mean over the ranks of each logged loss value (every rank has the same keys at a step)."""
        if not self.enabled or not values:
            return values
        keys = list(values)
        vec = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=self.device)
        self.all_reduce_(vec, f"the loss values' all-reduce of step {step}")
        return dict(zip(keys, (vec / self.world).tolist()))

    def reduce_strategy(self, strategy: Any, n: int, image_size: int, step: int) -> int:
        """Before a densification: the strategy's per-Gaussian statistics summed (and its maxima taken) over the
        ranks, through its own :meth:`reduce` (it knows what it holds); returns the batch's largest image side."""
        what = f"the density statistics' all-reduce of step {step}"
        return strategy.reduce(lambda t: self.all_reduce_(t, what),
                               lambda t: self.all_reduce_(t, what, dist.ReduceOp.MAX), n, image_size, self.device)

    def _fingerprint(self, tensors: Sequence[Tensor]) -> Tensor:
        """[2 per tensor + 1] float64 on the device: sum and position-weighted sum of each tensor, and the count
        of elements (equal tensors give equal fingerprints; a change anywhere almost surely changes them)."""
        parts = []
        for t in tensors:
            x = t.detach().reshape(-1).double()
            w = torch.arange(x.numel(), device=x.device, dtype=torch.float64).remainder_(1009).add_(1)
            parts += [x.sum(), (x * w).sum()]
        parts.append(torch.tensor(float(sum(t.numel() for t in tensors)), dtype=torch.float64, device=self.device))
        return torch.stack([p.to(self.device) for p in parts])

    def agree(self, tensors: Sequence[Tensor], what: str) -> bool:
        """Whether every rank holds the same ``tensors`` (fingerprints gathered and compared)."""
        if not self.enabled:
            return True
        mine = self._fingerprint(tensors)
        counts = torch.tensor([float(mine.numel())], dtype=torch.float64, device=self.device)
        self.all_reduce_(counts, f"comparing {what}", dist.ReduceOp.MAX)
        if int(counts) != mine.numel():  # a different number of tensors: pad, they differ anyway
            mine = torch.cat([mine, mine.new_full((int(counts) - mine.numel(),), float("nan"))])
        every = [torch.empty_like(mine) for _ in range(self.world)]
        with self._collective(f"comparing {what}"):
            dist.all_gather(every, mine)
        rows = [e.tolist() for e in every]
        return all(r == rows[0] for r in rows)

    def sync_gaussians(self, model: nn.Module, optimizer: torch.optim.Optimizer, step: int) -> bool:
        """After a density event: compare every rank's Gaussians with rank 0's, then broadcast rank 0's
        Gaussian parameters and their Adam moments (a rank whose count differs is resized first), so the ranks
        go on from identical models whatever the random draws of the event were. Returns whether they all
        agreed before the broadcast (recorded in the run's log). One flat buffer per dtype serves both the
        comparison (its fingerprint) and the broadcast: an event runs dozens of times a run, at every rank count."""
        groups = [g for g in optimizer.param_groups if g.get("name") in PARAM_NAMES]
        params = [g["params"][0] for g in groups]
        mine = params[0].shape[0]
        n = torch.tensor([float(mine)], dtype=torch.float64, device=self.device)
        self.broadcast_([n], "the Gaussian count")
        resized = int(n) != mine
        if resized:
            resize_gaussians(model, optimizer, int(n))
            groups = [g for g in optimizer.param_groups if g.get("name") in PARAM_NAMES]
        tensors: List[Tensor] = []
        for g in groups:
            p = g["params"][0]
            tensors.append(p.data)
            state = optimizer.state.get(p, {})
            tensors += [state[k] for k in ("exp_avg", "exp_avg_sq") if k in state]
        what = f"the Gaussians and their Adam moments after the density event of step {step}"
        flats = []
        for idx in self._flat_groups(tensors).values():
            parts = [tensors[i] for i in idx]
            flats.append((parts, torch.cat([t.detach().reshape(-1) for t in parts])))
        fingerprint = torch.cat([self._fingerprint([flat]) for _, flat in flats]
                                + [torch.tensor([float(len(tensors))], dtype=torch.float64, device=self.device)])
        every = [torch.empty_like(fingerprint) for _ in range(self.world)]
        with self._collective(f"comparing {what}"):
            dist.all_gather(every, fingerprint)
        for parts, flat in flats:
            with self._collective(f"receiving {what} from rank 0"):
                dist.broadcast(flat, src=0)
            with torch.no_grad():
                for t, chunk in zip(parts, flat.split([t.numel() for t in parts])):
                    t.copy_(chunk.view_as(t))
        rows = torch.stack(every).tolist()  # read after the broadcast is queued: one host sync, at the end
        return not resized and all(r == rows[0] for r in rows)

    # ---- set-up ------------------------------------------------------------------------------------------
    def decompose_shard(self, scene: Any, cfg: Config, device: str, progress: bool) -> None:
        """Fill the scene's decomposition cache in shards: this rank computes the missing entries of the
        training views ``i % N == rank`` (each entry is written atomically), then every rank waits for the
        others; the trainer then reads every view's entry from the cache."""
        if not self.enabled:
            return
        dcfg = cfg.decomposer
        needed = cfg.method in ("retinexgs", "pre") and dcfg.method != "none"
        mine = scene.train[self.rank::self.world] if needed else []
        if mine:
            from retinexgs.train.view_setup import denoise_spec  # the trainer's own choice of denoiser

            # The entries the trainer reads: under decomposer.denoise, the denoised views' (keyed by its recipe,
            # which every rank measures from the same views), else the plain ones.
            spec = denoise_spec(scene.train, cfg, device, views_per_point=scene.views_per_point)
            decompose_images([v.image_path for v in mine], dcfg.method, dict(dcfg.params) or None,
                             cache_dir=scene_cache_root(scene.root, cfg.data.cache_dir),
                             device=dcfg.device or device, keep=False, progress=progress and self.is_main,
                             cache_hint="--set data.cache_dir=DIR", sweep=False, raw_denoise=dcfg.raw.preview_denoise,
                             balance=mine[0].balance, names=[v.source_path or v.image_path for v in mine],
                             denoise=spec)
        self.barrier("every rank's share of the decomposition")

    def training_stats(self, batch: int, views: int, seconds: float, time_to_first_step: Optional[float],
                       params: Sequence[Tensor], timing: Optional[Dict[str, float]] = None) -> Dict[str, Any]:
        """The benchmark's figures of a training session (metrics.json["train"]), gathered from every rank:
        ranks, views per step, time to the end of the first step, peak GPU memory and host RSS per rank,
        views per second, and whether the ranks' parameters are identical at the end. ``timing`` (the trainer's
        ``first_step_seconds``, ``event_seconds``, ``event_steps``) adds the steady rate: views per second
        after the first step (its warm-up is in ``time_to_first_step`` already), and what the density events
        cost beyond a plain step's time (a fixed cost per run: the same events whatever the rank count)."""
        local: Dict[str, Any] = {"rss": round(max_rss_gb(), 3)}
        if self.device.type == "cuda":
            local["gpu"] = round(torch.cuda.max_memory_allocated(self.device) / 2**30, 3)
        rows = self.gather_objects(local, "the ranks' memory figures")
        out: Dict[str, Any] = {"ranks": self.world, "views_per_step": batch, "time_to_first_step": None,
                               "views_per_second": round(views / seconds, 3) if seconds > 0 else None,
                               "host_rss_gb_per_rank": [r["rss"] for r in rows]}
        if time_to_first_step is not None:
            out["time_to_first_step"] = round(time_to_first_step, 3)
        out.update(steady_timing(batch, views, seconds, timing))
        if self.device.type == "cuda":
            out["peak_gpu_memory_gb_per_rank"] = [r.get("gpu") for r in rows]
        out["ranks_in_sync"] = self.agree(list(params), "the parameters at the end of training")  # 1 rank: True
        return out

    # ---- tests -------------------------------------------------------------------------------------------
    def test_fault(self, step: int) -> None:
        """Tests only (RETINEXGS_TEST_DIE_AT_STEP / RETINEXGS_TEST_HANG_AT_STEP): this rank exits or hangs."""
        if self._fault is None or step != self._fault[1] or self.rank != self._fault[2]:
            return
        print(f"retinexgs train: test fault: {self.describe()} {'exits' if self._fault[0] == 'die' else 'hangs'} "
              f"at step {step}", file=sys.stderr, flush=True)
        if self._fault[0] == "die":
            os._exit(3)
        while True:
            time.sleep(3600)

    def close(self, ok: bool) -> None:
        """Leave the process group: after a barrier when the run ended well (no rank tears down while another
        still gathers); at once after an error (the others are stopped by torchrun or time out)."""
        if not self.enabled or not dist.is_initialized():
            return
        if ok:
            self.barrier("the end of the run")
            dist.destroy_process_group()


def shared_folder_problem(folder: Path, what: str, rows: Sequence[Tuple[bool, str]]) -> str:
    """The error for the ranks of ``rows`` ((saw rank 0's probe file, host name) per rank) that do not see
    ``folder`` as rank 0 does; '' when all do."""
    blind = [(r, host) for r, (seen, host) in enumerate(rows) if not seen]
    if not blind:
        return ""
    ranks = ", ".join(str(r) for r, _ in blind)
    hosts = ", ".join(sorted({host for _, host in blind}))
    return (f"{what} {folder} is not shared by every rank: rank{'s' if len(blind) > 1 else ''} {ranks} (on {hosts}) "
            f"cannot see the file rank 0 wrote there (on {rows[0][1]}). Training on several machines needs the "
            "scene's cache folder and the run folder on a file system every machine mounts at the same path (NFS, "
            "Lustre, ...); put the caches there with --set data.cache_dir=DIR and the run with --out")


def steady_timing(batch: int, views: int, seconds: float, timing: Optional[Dict[str, float]]) -> Dict[str, Any]:
    """The steady figures of a session of ``views`` views (``batch`` a step) in ``seconds``: views per second
    after the first step, and the density events' steps, seconds and overhead (their seconds less as many plain
    steps' time); {} without ``timing`` or its first step's time."""
    first = (timing or {}).get("first_step_seconds")
    steps = views // max(1, batch)
    if first is None or steps < 2 or seconds - first <= 0:
        return {}
    ev_s, ev_n = float(timing.get("event_seconds", 0.0)), int(timing.get("event_steps", 0))
    out: Dict[str, Any] = {"first_step_seconds": round(first, 3),
                           "views_per_second_after_first_step": round((views - batch) / (seconds - first), 3),
                           "density_event_steps": ev_n, "density_event_seconds": round(ev_s, 3)}
    plain_steps, plain_s = steps - 1 - ev_n, seconds - first - ev_s
    if plain_steps > 0 and plain_s > 0:
        out["plain_step_seconds"] = round(plain_s / plain_steps, 6)
        out["density_event_overhead_seconds"] = round(ev_s - ev_n * plain_s / plain_steps, 3)
    return out


def _test_fault() -> Optional[Tuple[str, int, int]]:
    for kind, env in (("die", TEST_DIE_ENV), ("hang", TEST_HANG_ENV)):
        step = _env_int(env)
        if step is not None:
            return kind, step, _env_int(TEST_FAULT_RANK_ENV) or 1
    return None


def init_from_env(device: str) -> Tuple[Distributed, str]:
    """(this process's Distributed, its device). Launched by torchrun with WORLD_SIZE > 1: joins the process
    group (env:// rendezvous from torchrun's MASTER_ADDR/PORT, RANK, WORLD_SIZE), NCCL on ``cuda:LOCAL_RANK``
    or gloo on the CPU, with the timeouts of the module docstring. Otherwise (no torchrun, or one rank) the
    plain run: no process group, ``device`` as given."""
    world = _env_int("WORLD_SIZE") or 1
    if world <= 1:
        return Distributed(device=torch.device(device), _fault=_test_fault()), device
    rank, local = _env_int("RANK") or 0, _env_int("LOCAL_RANK")
    local = rank if local is None else local
    timeout, setup_timeout = _env_seconds(TIMEOUT_ENV, DEFAULT_TIMEOUT), _env_seconds(SETUP_TIMEOUT_ENV,
                                                                                       DEFAULT_SETUP_TIMEOUT)
    if device.startswith("cuda"):
        visible = torch.cuda.device_count()
        if local >= visible:
            raise UserError(f"rank {rank} of {world} has LOCAL_RANK {local} but torch sees {visible} GPU(s) "
                            "(CUDA_VISIBLE_DEVICES): start at most one rank per visible GPU")
        torch.cuda.set_device(local)
        device, backend = f"cuda:{local}", "nccl"
    else:
        backend = "gloo"
    kwargs: Dict[str, Any] = {"backend": backend, "timeout": datetime.timedelta(seconds=timeout)}
    if backend == "nccl":
        kwargs["device_id"] = torch.device(device)
    ctx = Distributed(rank, world, local, backend, torch.device(device), timeout, setup_timeout,
                      _fault=_test_fault())
    with ctx._collective("joining the process group (torch.distributed.init_process_group)", setup=True):
        dist.init_process_group(**kwargs)
        ctx._host = dist.new_group(backend="gloo", timeout=datetime.timedelta(seconds=setup_timeout))
    return ctx, device


# ---- train --gpus N ------------------------------------------------------------------------------------------

def strip_gpus(argv: Sequence[str]) -> List[str]:
    """``argv`` without ``--gpus N`` / ``--gpus=N`` (or an abbreviation argparse accepts, e.g. ``--gpu``)."""
    out: List[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
            continue
        name = arg.split("=", 1)[0]
        if len(name) >= 3 and name.startswith("--") and "--gpus".startswith(name):
            skip = "=" not in arg
            continue
        out.append(arg)
    return out


def relaunch(n: int, device: str, argv: Sequence[str]) -> int:
    """Run ``retinexgs ARGV`` (``--gpus`` removed) on ``n`` ranks of this machine through
    ``python -m torch.distributed.run --standalone``: one per GPU, or ``n`` CPU processes (gloo) with
    ``--device cpu``. Returns torchrun's exit code. UserError for more ranks than visible GPUs."""
    if device == "cpu":
        cores = os.cpu_count() or 1
        # Each CPU rank runs its own kernels' threads: with more ranks than cores they only take turns.
        print(f"--gpus {n} --device cpu: {n} training processes on the CPU (gloo), for testing data-parallel "
              f"training; {cores} CPU core{'s' if cores != 1 else ''} here, so each rank gets "
              + (f"about {cores // n} of them" if cores >= n else "a share of one, slower than one process"),
              file=sys.stderr)
    elif device in ("auto", "cuda"):
        visible = torch.cuda.device_count()
        if visible == 0:
            raise UserError(f"--gpus {n}: torch sees no CUDA GPU (torch {torch.__version__}); --gpus {n} --device "
                            f"cpu runs {n} processes on the CPU (gloo), for testing")
        if n > visible:
            raise UserError(f"--gpus {n}: only {visible} GPU(s) are visible (CUDA_VISIBLE_DEVICES="
                            f"{os.environ.get('CUDA_VISIBLE_DEVICES', 'unset')}); use --gpus {visible} or fewer")
    else:
        raise UserError(f"--gpus {n} with --device {device}: the ranks use cuda:0..{n - 1} (choose the GPUs with "
                        "CUDA_VISIBLE_DEVICES) and --device cuda, auto, or cpu (gloo, for testing)")
    env = dict(os.environ)
    # The ranks import this copy of the package (a source checkout on sys.path, not another install).
    here = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = here + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(n),
           "-m", "retinexgs", *strip_gpus(argv)]
    proc = subprocess.Popen(cmd, env=env)
    try:
        return proc.wait()
    except BaseException:  # Ctrl-C or SIGTERM here: stop torchrun (it stops the ranks) before leaving
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        raise


def gradient_params(optimizer: torch.optim.Optimizer) -> List[Tensor]:
    """The optimiser's parameters in group order (the same order on every rank)."""
    return [p for group in optimizer.param_groups for p in group["params"]]


def take_gradients(params: Sequence[Tensor], acc: Optional[List[Optional[Tensor]]]) -> List[Optional[Tensor]]:
    """Move the gradients of one view out of ``p.grad`` into the running sum ``acc`` (a copy: a gradient may be
    a CUDA graph's static buffer, which the next view's replay overwrites)."""
    grads = [p.grad for p in params]
    if acc is None:
        acc = [None if g is None else g.clone() for g in grads]
    else:
        for i, g in enumerate(grads):
            if g is not None:
                acc[i] = g.clone() if acc[i] is None else acc[i].add_(g)
    for p in params:
        p.grad = None
    return acc

