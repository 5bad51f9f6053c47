"""Studies of the tracker: simulated scenes, metrics (Score eq. 18, GOSPA, OSPA, purity), Appendix B
comparisons, the paper's experiment (local or on Dask), regimes, the 1-D example (:mod:`tracker.study.oned`,
imported as a module) and their figures. Names load on first use: matplotlib, pandas and dask only when asked."""

from common.exports import lazy_exports

_EXPORTS = {
    "best_tau_index": "compare",
    "prob_better": "compare",
    "compare": "compare",
    "comparison_table": "compare",
    "parse_taus": "experiment",
    "ExperimentConfig": "experiment",
    "CachedIntegrator": "experiment",
    "run_dataset": "experiment",
    "run_experiment": "experiment",
    "score_matrix": "experiment",
    "summarise": "experiment",
    "write_outputs": "experiment",
    "run_and_write": "experiment",
    "ScoreGram": "metrics",
    "posterior_means": "metrics",
    "mixture_weights": "metrics",
    "score": "metrics",
    "gospa": "metrics",
    "ospa": "metrics",
    "purity": "metrics",
    "score_figure": "plots",
    "nd_error_figure": "plots",
    "overview_figure": "plots",
    "table_markdown": "plots",
    "write_figures": "plots",
    "tracks_figure": "plots",
    "brute_force_pairs": "projections",
    "predicted_choice": "projections",
    "measure_projections": "projections",
    "scaled_sensor": "regimes",
    "report_spread_m": "regimes",
    "best_tau_summary": "regimes",
    "regime_grid": "regimes",
    "AirborneSensor": "simulate",
    "Scenario": "simulate",
    "central_windows": "simulate",
    "simulate": "simulate",
    "run_experiment_dask": "sweep",
    "run_and_write_dask": "sweep",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
