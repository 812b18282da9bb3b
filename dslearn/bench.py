"""``dslearn-bench``: benchmarks that print figures (not timed tests).

Workloads:
  gp        online GP step (predict + append, S nodes) at data-set sizes n, against a reference
            that refactorises K from scratch (torch.linalg.cholesky) at every step, in the same process.
  protocol  the Yu Table I + II protocol (250 episodes: 200 train + 50 test) for every model x
            fusion of ``--models`` / ``--fusions``, one after the other in this process.

Results: a table printed as Markdown and written to ``--out`` (CSV + Markdown).
"""

from __future__ import annotations

import argparse
import platform
import resource
import time
from pathlib import Path

import pandas as pd
import torch

from .io import atomic_write_csv, atomic_write_text


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_gp(sizes=(600, 2400), nodes=10, dim=8, steps=20) -> list[dict]:
    from .models.gp import OnlineGP

    rows = []
    gen = torch.Generator().manual_seed(0)
    for n in sizes:
        gp = OnlineGP(nodes, dim, dim, capacity=n + steps + 1)
        X = torch.randn(n, nodes, dim, generator=gen, dtype=torch.float64)
        for i in range(n):
            gp.append(X[i], torch.sin(X[i]))
        xs = torch.randn(steps, nodes, dim, generator=gen, dtype=torch.float64)
        t0 = time.perf_counter()
        for i in range(steps):
            gp.predict(xs[i].unsqueeze(1))
            gp.append(xs[i], torch.sin(xs[i]))
        inc = (time.perf_counter() - t0) / steps
        # reference: refit from scratch (kernel matrix + Cholesky + solves) every step
        Xr = gp.X[:, : gp.n].clone()
        t0 = time.perf_counter()
        ref_steps = max(2, steps // 5)
        for i in range(ref_steps):
            K = gp.kernel(Xr, Xr) + 0.25 * torch.eye(Xr.shape[1], dtype=torch.float64)
            L = torch.linalg.cholesky(K)
            a = torch.cholesky_solve(torch.sin(Xr), L)
            ks = gp.kernel(Xr, xs[i].unsqueeze(1))
            _ = ks.transpose(-1, -2) @ a, torch.linalg.solve_triangular(L, ks, upper=False)
        ref = (time.perf_counter() - t0) / ref_steps
        rows.append(
            dict(workload=f"gp step n={n}", nodes=nodes, wall_s=inc * steps, ms_per_step=1e3 * inc,
                 ms_per_step_node=1e3 * inc / nodes, reference_ms_per_step=1e3 * ref, speedup=ref / inc,
                 peak_mb=_peak_mb())
        )
    return rows


def bench_protocol(models, fusions, train=200, test=50) -> list[dict]:
    from hydra import compose, initialize_config_dir

    from .run import CONF_DIR
    from .studies.yu import YuStudy

    rows = []
    for model in models:
        for fusion in fusions:
            with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
                cfg = compose(
                    "config",
                    overrides=[f"model={model}", f"consensus={fusion}", f"data.train_episodes={train}", f"data.test_episodes={test}"],
                )
            t0 = time.perf_counter()
            df = YuStudy.from_config(cfg).run()
            wall = time.perf_counter() - t0
            steps = (train if model.startswith("gp") else 0) + test  # episodes filtered
            avg = df[(df["node_kind"] == "sensor") & (df["metric"] == "track_err")]["value"].mean()
            rows.append(dict(workload=f"yu {model}/{fusion} {train}+{test}", nodes=10, wall_s=wall,
                             ms_per_step=1e3 * wall / max(1, steps * 12), track_err=avg, peak_mb=_peak_mb()))
            print(f"  {rows[-1]['workload']}: {wall:.1f}s", flush=True)
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="dslearn-bench", description="dslearn benchmarks (print figures)")
    p.add_argument("workloads", nargs="*", default=["gp"], choices=["gp", "protocol"])
    p.add_argument("--models", default="lin,sfm,gp,gp_increment")
    p.add_argument("--fusions", default="individual,hybrid")
    p.add_argument("--train", type=int, default=200)
    p.add_argument("--test", type=int, default=50)
    p.add_argument("--sizes", default="600,2400")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="bench")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    rows = []
    t0 = time.perf_counter()
    if "gp" in a.workloads:
        rows += bench_gp(tuple(int(s) for s in a.sizes.split(",")))
    if "protocol" in a.workloads:
        rows += bench_protocol(a.models.split(","), a.fusions.split(","), a.train, a.test)
    total = time.perf_counter() - t0
    df = pd.DataFrame(rows)
    df["machine"] = f"{platform.machine()} {torch.get_num_threads()} thread(s), torch {torch.__version__}"
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    from .report import markdown

    md = markdown(df.round(4))
    atomic_write_csv(df, out / "bench.csv")
    atomic_write_text(out / "bench.md", md + "\n")
    print(md)
    print(f"\ntotal {total:.1f}s; wrote {out / 'bench.csv'}")


if __name__ == "__main__":
    main()
