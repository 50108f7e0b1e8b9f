"""The exposure meter's white point on the GPU: one order statistic of every pixel's peak, by torch.kthvalue, by
torch.topk's least (what retinexgs/model/tones/meter.py uses) and by a full sort, at fox-dark's, a 3 MP and a 12 MP
image's pixel count (issue 65: kthvalue took 76 ms of a 12 MP step). Each: the median of 20 timed calls (CUDA
events) after 3 warm-ups, the three values compared, and topk's form captured in a CUDA graph and replayed.

    python experiments/meter_select_probe.py [--sizes 230400,3000000,12000000] [--share 0.05]
"""
from __future__ import annotations

import argparse
import statistics

import torch


def timed(fn, reps: int = 20) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(reps):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        b.synchronize()
        times.append(a.elapsed_time(b) * 1000)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="230400,3000000,12000000")
    ap.add_argument("--share", type=float, default=0.05)
    args = ap.parse_args()
    g = torch.Generator(device="cuda").manual_seed(0)
    print("| pixels | kthvalue µs | topk's least µs | sort µs | same value | topk in a graph µs |")
    print("|---|---|---|---|---|---|")
    for n in (int(s) for s in args.sizes.split(",")):
        peak = torch.rand(n, device="cuda", generator=g) ** 3
        rank = min(n - 1, max(0, int(round((1.0 - args.share) * (n - 1)))))
        forms = {"kth": lambda: torch.kthvalue(peak, rank + 1).values,
                 "topk": lambda: torch.topk(peak, n - rank, sorted=False).values.min(),
                 "sort": lambda: torch.sort(peak).values[rank]}
        t = {k: timed(f) for k, f in forms.items()}
        same = len({float(f()) for f in forms.values()}) == 1
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            forms["topk"]()
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            out = forms["topk"]()
        graph.replay()
        torch.cuda.synchronize()
        assert float(out) == float(forms["kth"]()), "the captured topk differs"
        tg = timed(graph.replay)
        print(f"| {n:,} | {t['kth']:.0f} | {t['topk']:.0f} | {t['sort']:.0f} | {same} | {tg:.0f} |")


if __name__ == "__main__":
    main()
