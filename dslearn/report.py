"""``dslearn-report DIR``: gather a run or multirun directory into paper-shaped tables and figures.

``DIR`` is a run directory, a sweep directory (its gathered ``sweep_results.parquet``/``.csv`` is
used when present, else every complete job's ``results.csv``; broken job dirs are skipped with a
warning) or the path of a gathered table itself. Writes ``summary.csv`` (columns
``study, consensus, node, model, metric, mean, std, n`` plus every other key column), and when
several seeds are present ``summary_seeds.csv`` (per-seed means, then mean ± std over seeds),
the generic ``tables.md`` / ``tables.tex`` (one table per metric, mean ± std) and one PNG per
metric, each study's own Markdown/CSV tables and PNG figures, and prints the Markdown.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

import pandas as pd

from .errors import DataFormatError
from .io import atomic_write_csv, atomic_write_text, load_results

#: columns that are not keys: values, replicates, and bookkeeping of gathered sweeps
NON_KEYS = {"value", "episode", "seed", "run_dir", "job", "ov.seed"}
REQUIRED = ["study", "consensus", "node", "model", "metric"]


def _redundant_override(c: str, columns) -> bool:
    """``ov.<key>`` of a gathered sweep that the results already carry as a column
    (``ov.model`` -> ``model``, ``ov.consensus.omega`` -> ``omega``): not a separate key, so that
    runs the study itself labels alike (e.g. ``individual`` under either ω) are pooled as before."""
    if not c.startswith("ov."):
        return False
    k = c[3:]
    return k in columns or k.split(".")[-1] in columns


def key_columns(df: pd.DataFrame) -> list[str]:
    keys = [c for c in df.columns if c not in NON_KEYS and not _redundant_override(c, df.columns)]
    return REQUIRED + [c for c in keys if c not in REQUIRED]


def summarize(results: pd.DataFrame) -> pd.DataFrame:
    """Mean, std, n over episodes (and seeds) for every key combination.

    Where a ``node_kind`` column marks sensing nodes, an ``avg`` node is added: per episode the
    mean over sensing nodes, then mean/std over episodes (the paper's "Average" row).
    """
    df = results.copy()
    for c in REQUIRED:
        if c not in df.columns:
            df[c] = "-"
    keys = key_columns(df)
    for c in keys:
        if df[c].isna().any():
            df[c] = df[c].astype(object).where(df[c].notna(), "-")
    parts = [df]
    if "node_kind" in df.columns and (df["node_kind"] == "sensor").any():
        sens = df[df["node_kind"] == "sensor"]
        gk = [k for k in keys if k not in ("node", "node_kind")] + [c for c in ("episode", "seed") if c in df.columns]
        avg = sens.groupby(gk, dropna=False, sort=False)["value"].mean().reset_index()
        avg["node"] = "avg"
        avg["node_kind"] = "avg"
        parts.append(avg)
    full = pd.concat(parts, ignore_index=True)
    g = full.groupby(keys, dropna=False, sort=False)["value"]
    out = g.agg(mean="mean", std="std", n="count").reset_index()
    cols = REQUIRED + ["mean", "std", "n"] + [k for k in keys if k not in REQUIRED]
    return out[cols]


def console_table(summary: pd.DataFrame) -> str:
    """A compact table of one run: rows node, columns metric, cells mean ± std."""
    s = summary.copy()
    extra = [c for c in ("train_seen",) if c in s.columns]
    if extra:
        s = s[s[extra[0]] == s[extra[0]].max()]
    s["cell"] = s["mean"].map("{:.3f}".format) + " ± " + s["std"].map("{:.3f}".format)
    head = ", ".join(f"{c}={s[c].iloc[0]}" for c in ("study", "model", "consensus") if c in s.columns)
    tab = s.pivot_table(index="node", columns="metric", values="cell", aggfunc="first", sort=False)
    return f"{head}\n{tab.to_markdown() if _has_tabulate() else tab.to_string()}"


def _has_tabulate() -> bool:
    try:
        import tabulate  # noqa: F401

        return True
    except ImportError:
        return False


def markdown(df: pd.DataFrame) -> str:
    """DataFrame -> GitHub Markdown table (no extra dependency)."""
    cols = [str(c) for c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for row in df.itertuples(index=False):
        lines.append("| " + " | ".join(str(v) for v in row) + " |")
    return "\n".join(lines)


def seed_summary(results: pd.DataFrame) -> pd.DataFrame | None:
    """Mean ± std over seeds: per seed the mean over episodes, then across seeds (``None`` with one seed)."""
    if "seed" not in results.columns or results["seed"].nunique() < 2:
        return None
    df = results.copy()
    for c in REQUIRED:
        if c not in df.columns:
            df[c] = "-"
    keys = [k for k in key_columns(df)]
    for c in keys:
        if df[c].isna().any():
            df[c] = df[c].astype(object).where(df[c].notna(), "-")
    per_seed = df.groupby(keys + ["seed"], dropna=False, sort=False)["value"].mean().reset_index()
    out = per_seed.groupby(keys, dropna=False, sort=False)["value"].agg(mean="mean", std="std", n_seeds="count")
    return out.reset_index()


def metric_tables(summary: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """One table per metric: rows = the key columns that vary, cell = ``mean ± std``.

    Where the summary has an ``avg`` node (the paper's "Average" row) only that node is shown.
    """
    s = summary.copy()
    if "node" in s.columns and (s["node"] == "avg").any():
        s = s[s["node"] == "avg"]
    keys = [c for c in s.columns if c not in ("metric", "mean", "std", "n", "n_seeds") and s[c].nunique(dropna=False) > 1]
    keys = [c for c in keys if not (c.startswith("ov.") and c[3:] in s.columns)]  # override = a column already
    out = {}
    for metric, g in s.groupby("metric", sort=False):
        cell = g["mean"].map("{:.4g}".format) + " ± " + g["std"].map(lambda v: "-" if pd.isna(v) else f"{v:.2g}")
        t = g[keys].copy() if keys else pd.DataFrame(index=g.index)
        t["mean ± std"] = cell.values
        n = "n_seeds" if "n_seeds" in g.columns else "n"
        t[n] = g[n].values
        out[str(metric)] = t.reset_index(drop=True)
    return out


def to_latex(df: pd.DataFrame, caption: str) -> str:
    """A LaTeX table (``DataFrame.to_latex``; plain tabular fallback without jinja2)."""
    try:
        body = df.to_latex(index=False, caption=caption.replace("_", r"\_"), escape=True)
        return body.replace("±", r"$\pm$")
    except ImportError:
        cols = " & ".join(str(c) for c in df.columns)
        rows = " \\\n".join(" & ".join(str(v) for v in r) for r in df.itertuples(index=False))
        return f"\\begin{{tabular}}{{{'l' * len(df.columns)}}}\n{cols} \\\\\n\\hline\n{rows} \\\\\n\\end{{tabular}}\n"


def _plot_metric(table: pd.DataFrame, metric: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [c for c in table.columns if c not in ("mean ± std", "n", "n_seeds")]
    labels = [" ".join(str(v) for v in r) for r in table[keys].itertuples(index=False)] if keys else ["all"] * len(table)
    cells = table["mean ± std"].str.split(" ± ", expand=True)
    mean = pd.to_numeric(cells[0], errors="coerce")
    std = pd.to_numeric(cells[1], errors="coerce").fillna(0.0)
    fig, ax = plt.subplots(figsize=(max(4.0, 0.45 * len(table) + 2), 3.2))
    ax.bar(range(len(table)), mean, yerr=std, capsize=3, color="#4c72b0")
    ax.set_xticks(range(len(table)))
    ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(metric)
    ax.set_title(f"{metric} (mean ± std)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def generic_tables(summary: pd.DataFrame, out_dir: Path, figures: bool = True) -> str:
    """``tables.md``, ``tables.tex`` and ``<metric>.png`` for any tidy summary; returns the Markdown."""
    md, tex = [], []
    for metric, t in metric_tables(summary).items():
        md.append(f"### {metric}\n\n{markdown(t)}")
        tex.append(to_latex(t, f"{metric}: mean $\\pm$ std"))
        if figures:
            _plot_metric(t, metric, out_dir / f"{metric}.png")
    text = "\n\n".join(md)
    atomic_write_text(out_dir / "tables.md", text + "\n")
    atomic_write_text(out_dir / "tables.tex", "\n\n".join(tex))
    return text


def report(root: str | Path, out_dir: str | Path | None = None) -> str:
    root = Path(root)
    out = Path(out_dir) if out_dir is not None else (root.parent if root.is_file() else root)
    out.mkdir(parents=True, exist_ok=True)
    results = load_results(root)
    summary = summarize(results)
    atomic_write_csv(summary, out / "summary.csv")
    seeds = seed_summary(results)
    if seeds is not None:
        atomic_write_csv(seeds, out / "summary_seeds.csv")
    texts = []
    tasks = results["task"].dropna().unique() if "task" in results.columns else []
    for task in tasks:
        try:
            mod = importlib.import_module(f"dslearn.studies.{task}")
        except ImportError:
            continue
        fn = getattr(mod, "report", None)
        if fn is not None:
            sub = results[results["task"] == task]
            texts.append(fn(sub, summary[summary.get("task", task) == task] if "task" in summary else summary, out))
    generic = generic_tables(seeds if seeds is not None else summary, out, figures=not any(texts))
    text = "\n\n".join(t for t in texts if t) or generic
    atomic_write_text(out / "report.md", text + "\n")
    return text


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="dslearn-report", description=__doc__.splitlines()[0])
    p.add_argument("dir", help="a run or sweep output directory, or a gathered sweep_results.{parquet,csv}")
    p.add_argument("--out", default=None, help="write the tables/figures here (default: DIR)")
    a = p.parse_args(argv)
    try:
        print(report(a.dir, a.out))
    except (FileNotFoundError, DataFormatError) as e:
        print(f"dslearn-report: {e}", file=sys.stderr)
        raise SystemExit(2)
    where = Path(a.out) if a.out else (Path(a.dir).parent if Path(a.dir).is_file() else Path(a.dir))
    print(f"\nwrote {where / 'summary.csv'}, tables.md/.tex and the figures beside it")


if __name__ == "__main__":
    main()
