"""The reference paper's Table 2 beside this run's figures (``odometry --compare``)."""

from __future__ import annotations

PAPER_TABLE = {"proposed": (4.2, 3.054, 99.92), "SFM": (108.99, 60.717, 97.89), "NRSFM": (93.69, 49.589, 98.19)}


def format_table(reports: dict[str, dict]) -> str:
    def mm(v):
        return "n/a" if v is None else f"{v * 1000:.2f}"

    def pct(v):
        return "n/a" if v is None else f"{v:.2f}"

    names = list(reports)
    head = ["Parameters"] + [f"{n} (ours)" for n in names] + ["paper proposed", "paper SFM"]
    rows = [
        ["Total error (mm)"] + [mm(reports[n].get("end_error_m")) for n in names]
        + [str(PAPER_TABLE["proposed"][0]), str(PAPER_TABLE["SFM"][0])],
        ["RMSE (mm)"] + [mm(reports[n].get("ate_rmse_m")) for n in names]
        + [str(PAPER_TABLE["proposed"][1]), str(PAPER_TABLE["SFM"][1])],
        ["Accuracy (%)"] + [pct(reports[n].get("accuracy_pct")) for n in names]
        + [str(PAPER_TABLE["proposed"][2]), str(PAPER_TABLE["SFM"][2])],
        ["Path length (m)"] + [pct(reports[n].get("path_length_m")) for n in names] + ["5.12", "5.12"],
    ]
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    line = "+" + "+".join("-" * (w + 2) for w in widths) + "+"
    out = [line, "| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |", line]
    out += ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in rows]
    out.append(line)
    if "sfm" in reports:
        out.append("sfm uses the ground-truth step length (oracle scale).")
    return "\n".join(out)
