"""Both trajectories of an evaluation drawn to a PNG: a top view and a side view (matplotlib).

The ground truth is drawn as it is; the whole estimate (matched or not) after the evaluation's
alignment. World frames differ between sources (TUM's mocap is z up, KITTI's and a camera's
frame y down), so the views are chosen from the ground truth's extent: the top view spans its
two widest axes, the side view the widest against the narrowest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.geometry.evaluation import apply_similarity
from services.recorder.scoring import Evaluation

__all__ = ["plot_evaluation", "view_axes"]

AXES = "xyz"


def view_axes(positions: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    """``((a, b), (a, c))``: axis indices of the top and side views of (N, 3) positions, ``a`` the widest
    axis, ``b`` the next and ``c`` the narrowest."""
    a, b, c = np.argsort(-np.ptp(np.asarray(positions).reshape(-1, 3), axis=0), kind="stable")
    return (int(a), int(b)), (int(a), int(c))


def plot_evaluation(evaluation: Evaluation, out: Path | str) -> None:
    """Write the top and side views of ``evaluation``'s trajectories to the PNG ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = evaluation.gt.poses[:, :3, 3]
    est = apply_similarity(evaluation.score.ate.alignment, evaluation.est.poses)[:, :3, 3]
    figure, panels = plt.subplots(1, 2, figsize=(12, 5.5))
    for panel, (u, v), title in zip(panels, view_axes(gt), ("top view", "side view"), strict=True):
        panel.plot(gt[:, u], gt[:, v], "-", color="0.6", linewidth=3, label=f"ground truth ({len(gt)})")
        panel.plot(est[:, u], est[:, v], "-", color="tab:red", linewidth=1, label=f"estimate ({len(est)})")
        panel.set_xlabel(f"{AXES[u]} (m)")
        panel.set_ylabel(f"{AXES[v]} (m)")
        panel.set_title(title)
        panel.set_aspect("equal", adjustable="datalim")
        panel.grid(True, linewidth=0.3)
    panels[0].legend(loc="best")
    score = evaluation.score
    figure.suptitle(f"ATE rmse {score.ate.stats.rmse:.4f} m after {score.align} alignment"
                    + (f" (scale {score.ate.alignment.s:.4f})" if score.align == "sim3" else ""))
    figure.tight_layout()
    try:
        figure.savefig(out, dpi=100)
    except OSError as exc:
        raise ValueError(f"cannot write {out}: {exc.strerror or exc}") from exc
    finally:
        plt.close(figure)
