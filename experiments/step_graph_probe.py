"""Probe (issue 65): what a fox-dark step costs when captured whole as one CUDA graph.

The training step is bound by the host (``scripts/profiling.py train --slack``: 500 µs more host work a step
lengthens it by 430-740 µs, 500 µs more GPU work by 220-320 µs). A step captured whole (render, every loss,
backward, density statistics, optionally Adam) and replayed costs the host one launch. This probe measures, on one
training view of a trainer warmed up for ``--steps`` steps, the time a step takes:

- ``trainer``: the trainer's own step (today: eager render + three CUDA graphs + eager Adam);
- ``eager``: the same step with no graphs at all (the render, loss and backward as the capture sees them);
- ``graph fwd+bwd``: render + loss + backward + density statistics replayed as one graph, Adam eager;
- ``graph step``: the same with Adam inside the graph.

and checks that one replay's gradients equal the eager step's on the same parameters. The camera, the pair buffer's
capacity, the learning rates and Adam's bias corrections are baked into the graph here (one view, a few hundred
steps): the probe prices the capture, it is not a training loop. Needs a CUDA GPU.

    python experiments/step_graph_probe.py SCENE [--steps 3000] [--iters 300]
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time
import traceback
from pathlib import Path

import torch


class _FixedPairs:
    """A PairBudget stand-in: a fixed pair capacity, no late read (an event and a host copy cannot be captured)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity

    def plan(self, n, device, size=None):
        return self.capacity

    def observe(self, count, capacity) -> None:
        pass

    def observe_synced(self, pairs) -> None:
        pass

    def reset(self) -> None:
        pass


def _timed(fn, iters: int) -> float:
    """Milliseconds a call of ``fn`` over ``iters`` calls, the GPU drained before and after."""
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(iters):
        fn()
    torch.cuda.synchronize()
    return (time.perf_counter() - t0) / iters * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--iters", type=int, default=300)
    args = ap.parse_args()

    from retinexgs.run.config import load_config
    from retinexgs.run.folder import open_scene
    from retinexgs.train.trainer import Trainer

    cfg = load_config([], [f"loss.enhance_from={args.steps // 2}"])
    scene = open_scene(args.scene, cfg)
    with tempfile.TemporaryDirectory() as run:
        tr = Trainer(cfg, scene, Path(run), "cuda", progress=False, log=lambda s: None)
        tr.train(stop_after=args.steps)
        tr.save = lambda: None
        step = tr.step + 1
        while tr.strategy.edits_at(step) or tr.strategy.will_edit(step) or step % 100 == 0:
            step += 1
        tv = tr.views[0]
        n = len(tr.model.gaussians)
        print(f"{n} Gaussians after {tr.step} steps; view 0 at {tv.camera.width}x{tv.camera.height}; step {step}")

        state = {k: v.detach().clone() for k, v in tr.model.state_dict().items()}
        opt_state = {id(p): {k: (v.clone() if torch.is_tensor(v) else v) for k, v in tr.optimizer.state[p].items()}
                     for g in tr.optimizer.param_groups for p in g["params"]}

        def restore() -> None:
            with torch.no_grad():
                tr.model.load_state_dict(state)
            for g in tr.optimizer.param_groups:
                for p in g["params"]:
                    for k, v in opt_state[id(p)].items():
                        if torch.is_tensor(v):
                            tr.optimizer.state[p][k].copy_(v)
                        else:
                            tr.optimizer.state[p][k] = v

        rows = {}
        rows["trainer"] = _timed(lambda: tr.train_step(step, tv, check=False), args.iters)
        restore()

        seen = max(tr.pairs._max_seen.values()) if tr.pairs._max_seen else None
        if seen is None:
            tr.train_step(step, tv, check=True)
            seen = max(tr.pairs._max_seen.values())
        tr.pairs = _FixedPairs(math.ceil(1.5 * seen))
        w, h = tv.camera.width, tv.camera.height

        def fwd_bwd() -> torch.Tensor:
            res = tr.render_view(tv, step, graphed=False)
            terms = tr.objective.loss(res, tv, step)
            terms["total"].backward()
            tr.strategy.after_backward(res["out"], w, h)
            return terms["total"].detach()

        def eager_step() -> None:
            fwd_bwd()
            tr.optimizer.step()
            tr.optimizer.zero_grad(set_to_none=True)

        rows["eager"] = _timed(eager_step, args.iters)
        restore()

        # Gradients of one eager fwd+bwd, the reference for the replays.
        tr.optimizer.zero_grad(set_to_none=True)
        fwd_bwd()
        params = [p for g in tr.optimizer.param_groups for p in g["params"]]
        ref = [None if p.grad is None else p.grad.clone() for p in params]
        tr.optimizer.zero_grad(set_to_none=True)
        restore()

        for name, with_adam in (("graph fwd+bwd", False), ("graph step", True)):
            try:
                side = torch.cuda.Stream()
                side.wait_stream(torch.cuda.current_stream())
                with torch.cuda.stream(side):
                    for _ in range(3):
                        tr.optimizer.zero_grad(set_to_none=True)
                        fwd_bwd()
                torch.cuda.current_stream().wait_stream(side)
                restore()
                tr.optimizer.zero_grad(set_to_none=True)
                tr.model.near_plane()  # the near plane is read once per change of its buffer (restore changed it)
                g = torch.cuda.CUDAGraph()
                t0 = time.perf_counter()
                with torch.cuda.graph(g):
                    total = fwd_bwd()
                    if with_adam:
                        tr.optimizer.step()
                torch.cuda.synchronize()
                capture_ms = (time.perf_counter() - t0) * 1e3
                if not with_adam:
                    restore()
                    g.replay()
                    torch.cuda.synchronize()
                    worst = 0.0
                    for p, r in zip(params, ref):
                        if p.grad is None or r is None:
                            continue
                        worst = max(worst, float((p.grad - r).abs().max() / r.abs().max().clamp_min(1e-30)))
                    print(f"{name}: capture {capture_ms:.0f} ms; one replay's gradients vs eager: largest "
                          f"difference {worst:.2e} of each gradient's largest value; loss {float(total):.6f}")

                    def replay_then_adam() -> None:
                        g.replay()
                        tr.optimizer.step()
                    rows[name] = _timed(replay_then_adam, args.iters)
                else:
                    print(f"{name}: capture {capture_ms:.0f} ms")
                    rows[name] = _timed(g.replay, args.iters)
                restore()
                del g
                tr.optimizer.zero_grad(set_to_none=True)
            except Exception as err:  # report and go on: the probe's point is which capture works
                print(f"{name}: FAILED: {type(err).__name__}: {str(err).splitlines()[0][:300]}")
                traceback.print_exc(limit=6)
                torch.cuda.synchronize()

        base = rows["trainer"]
        print(f"ms a step on view 0 ({args.iters} steps each):")
        for k, v in rows.items():
            print(f"  {k:14s} {v:6.3f} ms  ({v / base:.2f}x the trainer's)")


if __name__ == "__main__":
    main()
