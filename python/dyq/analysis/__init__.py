"""Simulator-free analysis for profiling and calibrating the dispatcher (docs/profiling.md).

- :mod:`.stats`: Wilson intervals, the paired exact McNemar comparison, Pearson / Spearman and
  their bootstrap intervals;
- :mod:`.sensitivity`: the step-wise perturbation profile, s_t = D_T / e_t (Sec. III-A), and the
  proxies' correlation with it (Sec. III-B), with Figures 2 and 3;
- :mod:`.calibration`: lambda, D_acc / eta, Theta (Sec. IV-B, Eq. 5), K and theta_fp (Sec. VI-D),
  and the config file the dispatcher loads.

s_t itself is ``dyq.analysis.sensitivity.sensitivity(e, D)``: re-exported here, the function would
hide its module.
"""
from .calibration import (
    ThresholdCalibration,
    bound_parameters,
    calibrate_thresholds,
    choose_delay,
    choose_fusion_weight,
    choose_theta_fp,
    dispatch_trace,
    error_bound,
    write_config,
)
from .sensitivity import (
    ProfiledStep,
    Sensitivity,
    plot_perturbation_profile,
    plot_proxy_trajectories,
    proxy_correlations,
)
from .stats import BootstrapInterval, bootstrap_ci, mcnemar_exact, paired_comparison, pearson, spearman, wilson_interval

__all__ = [
    "BootstrapInterval",
    "ProfiledStep",
    "Sensitivity",
    "ThresholdCalibration",
    "bootstrap_ci",
    "bound_parameters",
    "calibrate_thresholds",
    "choose_delay",
    "choose_fusion_weight",
    "choose_theta_fp",
    "dispatch_trace",
    "error_bound",
    "mcnemar_exact",
    "paired_comparison",
    "pearson",
    "plot_perturbation_profile",
    "plot_proxy_trajectories",
    "proxy_correlations",
    "spearman",
    "wilson_interval",
]
