"""The robustness record's summary metrics (RR, mRR, CE, mCE, the share of the oracle), its
markdown report and its picture: NDS against severity for each condition family with the
oracle's curve, and bars for the conditions of no family."""
from __future__ import annotations

import math

import numpy as np

from clfbev import io

BASELINE_VARIANT = "concat"


def summarise(record: dict) -> None:
    """Add RR / mRR, the share of the oracle and, when a ``concat`` checkpoint is present,
    CE / mCE, in place."""
    conds, clean = record["conditions"], record["clean"]
    degraded = [c for c in conds if c != clean]
    base = next((n for n, m in record["models"].items() if m["variant"] == BASELINE_VARIANT), None)
    record["baseline"] = base
    oracle = record.get("oracle", {})
    for m in record["models"].values():
        nds0 = m["metrics"][clean]["NDS"]
        m["RR"] = {c: (m["metrics"][c]["NDS"] / nds0 if nds0 > 0 else math.nan) for c in conds}
        m["mRR"] = float(np.mean([m["RR"][c] for c in degraded])) if degraded else math.nan
        if oracle:
            m["share"] = {c: (m["metrics"][c]["NDS"] / oracle[c]["NDS"] if oracle[c]["NDS"] > 0 else math.nan)
                          for c in conds}
        if base is not None:
            b = record["models"][base]["metrics"]
            m["CE"] = {c: ((1 - m["metrics"][c]["NDS"]) / (1 - b[c]["NDS"]) if b[c]["NDS"] < 1 else math.nan)
                       for c in conds}
            m["mCE"] = float(np.mean([m["CE"][c] for c in degraded])) if degraded else math.nan


def _table(title: str, conds: list[str], rows: list[tuple[str, list[str]]]) -> list[str]:
    return ["", f"## {title}", "", "| model | " + " | ".join(conds) + " |", "|---|" + "---:|" * len(conds),
            *(f"| {name} | " + " | ".join(cells) + " |" for name, cells in rows)]


def markdown(record: dict) -> str:
    """The report: NDS (mAP) per model and condition with mRR and mCE, the oracle's row, then
    RR, CE and the share of the oracle per condition."""
    conds, models, oracle = record["conditions"], record["models"], record.get("oracle", {})
    lines = ["# Robustness", "",
             f"Split `{record['split']}`; clean reference `{record['clean']}`; official DetectionEval for every "
             f"cell. RR = NDS_c / NDS_clean; CE = (1 - NDS_c) / (1 - NDS_c of the `{BASELINE_VARIANT}` baseline"
             f"{' `' + record['baseline'] + '`' if record.get('baseline') else ', absent here'}); share = NDS_c / "
             "NDS_c of the oracle (the ground truth the condition's sensors still see, as predictions).", "",
             "## NDS (mAP)", "",
             "| model | variant | " + " | ".join(conds) + " | mRR | mCE |",
             "|---|---|" + "---:|" * (len(conds) + 2)]
    if oracle:
        cells = [f"{oracle[c]['NDS']:.4f} ({oracle[c]['mAP']:.4f})" for c in conds]
        lines.append("| oracle | - | " + " | ".join(cells) + " | - | - |")
    for name, m in models.items():
        cells = [f"{m['metrics'][c]['NDS']:.4f} ({m['metrics'][c]['mAP']:.4f})" for c in conds]
        mce = f"{m['mCE']:.3f}" if "mCE" in m else "-"
        lines.append(f"| {name} | {m['variant']} | " + " | ".join(cells) + f" | {m['mRR']:.3f} | {mce} |")
    lines += _table("RR per condition", conds, [(n, [f"{m['RR'][c]:.3f}" for c in conds]) for n, m in models.items()])
    if record.get("baseline"):
        lines += _table("CE per condition", conds, [(n, [f"{m['CE'][c]:.3f}" for c in conds]) for n, m in models.items()])
    if oracle:
        lines += _table("Share of the oracle's NDS", conds,
                        [(n, [f"{m['share'][c]:.3f}" for c in conds]) for n, m in models.items()])
        counts = [oracle[c]["counts"] for c in conds]
        lines += _table("What the oracle sees (annotations: by the lidar / by a camera / by either, of all)", conds,
                        [("oracle", [f"{k['lidar']} / {k['camera']} / {k['seen']} of {k['annotations']}" for k in counts])])
    lines += ["", "![NDS against severity per condition family, and the other conditions](robustness.png)", ""]
    return "\n".join(lines)


def curves(record: dict) -> dict[str, list[str]]:
    """{family: its conditions by severity, the clean reference first}."""
    out: dict[str, list[str]] = {}
    for c in record["conditions"]:
        family, _ = record["family"][c]
        if family is not None:
            out.setdefault(family, []).append(c)
    return {f: [record["clean"]] + sorted(cs, key=lambda c: record["family"][c][1]) for f, cs in out.items()}


def plot(record: dict, path) -> None:
    """One panel per condition family (NDS against severity, a line per model, the oracle
    dashed) and a bar chart of the conditions of no family, when there are any."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families = curves(record)
    bars = [c for c in record["conditions"] if c != record["clean"] and record["family"][c][0] is None]
    n_panels = len(families) + (1 if bars else 0)
    cols = min(n_panels, 4)
    rows = math.ceil(n_panels / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.5 * cols, 3.8 * rows), dpi=110, squeeze=False)
    axes = list(axes.ravel())
    for ax, (family, conds) in zip(axes, families.items()):
        _curve_panel(ax, record, family, conds)
    if bars:
        _bar_panel(axes[len(families)], record, bars)
    for ax in axes[n_panels:]:
        ax.set_visible(False)
    fig.tight_layout()
    io.save_figure(path, fig)
    plt.close(fig)


def _curve_panel(ax, record: dict, family: str, conds: list[str]) -> None:
    severity = [record["family"][c][1] for c in conds]
    oracle = record.get("oracle", {})
    if oracle:
        ax.plot(severity, [oracle[c]["NDS"] for c in conds], "k--", label="oracle")
    for name, m in record["models"].items():
        ax.plot(severity, [m["metrics"][c]["NDS"] for c in conds], "o-", label=f"{name} ({m['variant']})")
    ax.set_xlabel(f"{family} (0 = clean)")
    ax.set_ylabel("NDS")
    ax.set_title(f"NDS under {family}")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def _bar_panel(ax, record: dict, conds: list[str]) -> None:
    names = list(record["models"])
    width = 0.8 / len(names)
    x = np.arange(len(conds))
    for k, name in enumerate(names):
        ax.bar(x + k * width, [record["models"][name]["metrics"][c]["NDS"] for c in conds], width, label=name)
    oracle = record.get("oracle", {})
    if oracle:
        ax.hlines([oracle[c]["NDS"] for c in conds], x - width / 2, x + 0.8 - width / 2, colors="k",
                  linestyles="--", label="oracle")
    ax.set_xticks(x + width * (len(names) - 1) / 2)
    ax.set_xticklabels(conds, rotation=25, ha="right", fontsize=8)
    ax.set_ylabel("NDS")
    ax.set_ylim(0, 1.02)
    ax.set_title("failures, night, occlusion")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7)
