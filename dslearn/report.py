"""``dslearn-report DIR``: gather a run or multirun directory into paper-shaped tables and figures.

Writes ``DIR/summary.csv`` (columns ``study, consensus, node, model, metric, mean, std, n``
plus every other key column), each study's Markdown/CSV tables and PNG figures, and prints
the Markdown.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

import pandas as pd

from .io import atomic_write_csv, atomic_write_text, load_results

NON_KEYS = {"value", "episode", "seed", "run_dir"}
REQUIRED = ["study", "consensus", "node", "model", "metric"]


def key_columns(df: pd.DataFrame) -> list[str]:
    keys = [c for c in df.columns if c not in NON_KEYS]
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


def report(root: str | Path) -> str:
    root = Path(root)
    results = load_results(root)
    summary = summarize(results)
    atomic_write_csv(summary, root / "summary.csv")
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
            texts.append(fn(sub, summary[summary.get("task", task) == task] if "task" in summary else summary, root))
    text = "\n\n".join(t for t in texts if t) or markdown(summary)
    atomic_write_text(root / "report.md", text + "\n")
    return text


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="dslearn-report", description=__doc__.splitlines()[0])
    p.add_argument("dir", help="a run or multirun output directory")
    a = p.parse_args(argv)
    try:
        print(report(a.dir))
    except FileNotFoundError as e:
        print(f"dslearn-report: {e}", file=sys.stderr)
        raise SystemExit(2)
    print(f"\nwrote {Path(a.dir) / 'summary.csv'} and the tables/figures beside it")


if __name__ == "__main__":
    main()
