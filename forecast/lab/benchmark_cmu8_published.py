"""Published rows of the CMU 8-action benchmark, quoted with their source; none invented.

``PUBLISHED``: 3D MPJPE in the reference's millimetres at 80/160/320/400/560/1000 ms. ``OTHER_METRIC``: rows
on the same data in another metric (mean angle error), shown for context only, never compared with MPJPE.

LTD publishes no 560 ms value on CMU (None). siMLPe (Guo et al. 2023) reports Human3.6M, AMASS and 3DPW only
(its repository has no CMU code or table), so it has no row.
"""

from __future__ import annotations

ACTIONS = (
    "basketball", "basketball_signal", "directing_traffic", "jumping", "running", "soccer", "walking",
    "washwindow",
)  # fmt: skip

# MSR-GCN (Dang et al., ICCV 2021), README of github.com/Droliven/MSRGCN (commit 018c555), table
# "CMU-10/25/35-all": 10 observed frames, 25 forecast, 35 DCT coefficients, and scored on ALL test windows of
# each action ("on each we use all data instead of the random selected 8 samples"), not on the 8 windows of
# this protocol. The README's average row is quoted as printed.
_MSR = {
    "basketball": [10.24, 18.64, 36.94, 45.96, 61.12, 86.24],
    "basketball_signal": [3.04, 5.62, 12.49, 16.60, 25.43, 49.99],
    "directing_traffic": [6.13, 12.60, 29.37, 39.22, 60.46, 114.56],
    "jumping": [15.19, 28.85, 55.97, 69.11, 92.38, 126.16],
    "running": [13.17, 20.91, 29.88, 33.37, 38.26, 43.62],
    "soccer": [10.92, 19.40, 37.41, 47.00, 65.25, 101.85],
    "walking": [6.38, 10.25, 16.88, 20.05, 25.48, 36.78],
    "washwindow": [5.41, 10.93, 24.51, 31.79, 45.13, 70.16],
}

PUBLISHED: dict[str, dict] = {
    "LTD (Mao et al. 2019)": {
        "mpjpe_mm": [11.5, 20.4, 37.8, 46.8, None, 96.5],
        "windows": "the protocol's 8 per action, all 8 test files",
        "reruns_mpjpe_mm": [[11.3, 19.8, 36.9, 45.5, None, 92.7], [11.3, 19.7, 37.2, 46.0, None, 94.0]],
        "source": "github.com/wei-mao-2019/LearnTrajDep README.md (commit 47530723), section 'CMU-mocap', 3D "
        "coordinate rows (bottom half), row 'pre-trained' (the two re-runs 'test_run_1/2' kept beside it)",
    },
    "MSR-GCN (Dang et al. 2021)": {
        "mpjpe_mm": [8.81, 15.90, 30.43, 37.89, 51.69, 78.67],
        "per_action": _MSR,
        "windows": "all test windows of each action (not the protocol's 8)",
        "source": "github.com/Droliven/MSRGCN README.md (commit 018c5554), table 'CMU-10/25/35-all', "
        "row 'Average' and the 8 action rows",
    },
}

# Tanke 2024 (the seed), Table 6.7 'Mean Angular Error on CMU Mocap [1]': 80/160/320/400/1000 ms (no 560 ms);
# 'Trajectory [129]' is LTD (Mao et al. 2019) on joint angles. Average row as printed.
OTHER_METRIC: dict[str, dict] = {
    "LTD angles, 'Trajectory [129]' (Mao et al. 2019)": {
        "metric": "mean angle error",
        "horizons_ms": [80, 160, 320, 400, 1000],
        "average": [0.25, 0.39, 0.68, 0.79, 1.33],
        "source": "seed tanke-2024-context-aware-motion-anticipation.txt, Table 6.7, row 'Trajectory [129]'",
    },
    "Tanke 2024 (Ours, Table 6.7)": {
        "metric": "mean angle error",
        "horizons_ms": [80, 160, 320, 400, 1000],
        "average": [0.35, 0.52, 0.83, 0.96, 1.33],
        "source": "seed tanke-2024-context-aware-motion-anticipation.txt, Table 6.7, row 'Ours'",
    },
}


def average_over(per_action: dict[str, list[float]], actions: list[str]) -> list[float] | None:
    """The mean of the published per-action rows over ``actions`` (None when one is not published)."""
    if not all(a in per_action for a in actions):
        return None
    n = len(next(iter(per_action.values())))
    return [round(sum(per_action[a][k] for a in actions) / len(actions), 2) for k in range(n)]
