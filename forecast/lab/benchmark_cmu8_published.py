"""Published rows of the CMU 8-action benchmark, quoted with their source; none invented.

``PUBLISHED``: 3D MPJPE in the reference's millimetres at 80/160/320/400/560/1000 ms; ``all_windows``: scored
on every test window (protocol cmu8-all) rather than the protocol's 8 per file (cmu8). ``OTHER_METRIC``: rows
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

# PGBIG (Ma et al., CVPR 2022): the evaluation log of the repository's released CMU checkpoint,
# github.com/705062791/PGBIG (commit 9380daa), checkpoint/main_cmu_3d_all_in10_out25_ks10_dctn35_dropout_0.3_
# lr_0.005_d_model_16_e_6_d_6/test_all_eval.csv: columns #80, #160, #320, #400, #560, #1000 ms of each action
# row and of its 'avg' row, rounded to 0.01; scored on all test windows (option.json: test_sample_num -1).
_PGBIG = {
    "basketball": [9.53, 17.53, 35.32, 44.23, 59.41, 84.14],
    "basketball_signal": [2.71, 4.88, 10.77, 14.63, 23.69, 50.19],
    "directing_traffic": [4.83, 9.77, 23.62, 32.26, 51.60, 102.32],
    "jumping": [13.93, 27.78, 55.80, 69.01, 91.65, 125.60],
    "running": [12.69, 23.18, 38.31, 42.24, 44.98, 51.71],
    "soccer": [11.09, 20.63, 39.48, 48.72, 65.41, 99.98],
    "walking": [6.23, 10.34, 16.84, 19.76, 25.06, 33.93],
    "washwindow": [4.63, 9.16, 20.87, 27.35, 39.70, 65.69],
}

PUBLISHED: dict[str, dict] = {
    "LTD (Mao et al. 2019)": {
        "mpjpe_mm": [11.5, 20.4, 37.8, 46.8, None, 96.5],
        "all_windows": False,
        "windows": "the protocol's 8 per action, all 8 test files",
        "reruns_mpjpe_mm": [[11.3, 19.8, 36.9, 45.5, None, 92.7], [11.3, 19.7, 37.2, 46.0, None, 94.0]],
        "source": "github.com/wei-mao-2019/LearnTrajDep README.md (commit 47530723), section 'CMU-mocap', 3D "
        "coordinate rows (bottom half), row 'pre-trained' (the two re-runs 'test_run_1/2' kept beside it)",
    },
    "MSR-GCN (Dang et al. 2021)": {
        "mpjpe_mm": [8.81, 15.90, 30.43, 37.89, 51.69, 78.67],
        "per_action": _MSR,
        "all_windows": True,
        "windows": "all test windows of each action (not the protocol's 8)",
        "source": "github.com/Droliven/MSRGCN README.md (commit 018c5554), table 'CMU-10/25/35-all', "
        "row 'Average' and the 8 action rows",
    },
    "PGBIG (Ma et al. 2022)": {
        "mpjpe_mm": [8.20, 15.41, 30.13, 37.27, 50.19, 76.69],
        "per_action": _PGBIG,
        "all_windows": True,
        "windows": "all test windows of each action (test_sample_num -1)",
        "source": "github.com/705062791/PGBIG (commit 9380daa), checkpoint/main_cmu_3d_all_in10_out25_ks10_"
        "dctn35_dropout_0.3_lr_0.005_d_model_16_e_6_d_6/test_all_eval.csv, the 8 action rows and 'avg'",
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
