"""Learn here, track there (issue 16): a prior learned from past targets, scored on held-out real targets.

The region's target locations (a vector file: points or polygon centroids) are split into square
blocks of ``block_m`` metres dealt into ``n_folds`` folds (whole blocks per fold, as
:func:`pipeline.learn.block_folds` deals them). For each fold the terrain model and its hybrid are
fitted by :class:`pipeline.learn.PriorEstimator` on the targets *outside* the fold only. A data set is
one held-out block holding at least ``n_targets`` targets: its window is the block, its targets are
``n_targets`` of the block's locations picked at random (seeded), its reports come from the airborne
sensor as in the paper's experiment. No location is used both to learn and to score.

Every prior is tracked against on the same data sets (the same seed gives the same targets and
reports whatever the prior): the fold's learned terrain model (UU, UT, TT), its hybrid (TT), the
config's hand-set tables (TT), the learned density raised to α (r^α, TT: α = 0 is flat, α > 1
sharper than learned) and the model learned on another region's points, i.e. on the fold furthest
away, evaluated on this region's features (TT). Each prior is cut to a square of side 2·``block_m``
centred on the block (the block is its central half, as the paper keeps the central half of its
region) and renormalised there: the tracker's search area.

Metrics are against the real positions: GOSPA, OSPA, association purity, |N̂_D − N_D| and the RMS
error of the posterior means. Score (eq. 18) is against the perfect association under the prior
the row tracked with, so only the learned-prior rows (UU, UT, TT) share one reference: it is a
proxy (the real targets' prior is unknown) and compared only among them. Comparisons (Appendix B) pair each label at its own best τ:
by the metric's mean, except purity and the RMS error, read at the best-GOSPA τ (:data:`TAU_BY`).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from common.atomic import atomic_paths
from pipeline.prior import TerrainPrior
from tracker.study.compare import best_tau_index, prob_better
from tracker.study.experiment import (
    ExperimentConfig,
    map_local,
    parse_taus,
    run_dataset,
    write_results,
)
from tracker.study.simulate import AirborneSensor

ALPHAS = (0.0, 0.5, 1.0, 1.5, 2.0)
LEARNED = ("UU", "UT", "TT")
"""Variants run with the learned prior; every other prior runs TT only."""
BATCH = ("TT batch",)
"""Batch labels (with the learned prior): their Score shares the learned-prior rows' reference."""
METRICS = {"gospa_m": 1.0, "purity": -1.0, "ospa_m": 1.0, "nd_abs_error": 1.0, "rms_error_m": 1.0, "score": 1.0}
"""Compared metrics and their sign: +1 lower is better, -1 higher is better (purity)."""
HEADLINE = ("gospa_m", "purity")
TAU_BY = {"purity": "gospa_m", "rms_error_m": "gospa_m"}
"""Metrics read at the τ that is best for another: purity is 1 when every report starts its own target (τ
very negative) and the RMS error is smallest with few, well-fed tracks, so both are read at the label's
best-GOSPA τ (its operating point); every other metric at its own best τ."""


@dataclass(frozen=True)
class HeldoutConfig:
    """The learn-here-track-there experiment (see the module doc); lengths in metres."""

    region: str
    """Region TOML with the features, the hand-set tables and the [learn] settings."""
    targets_file: str
    targets_layer: str | None = None
    block_m: float = 2000.0
    n_folds: int = 5
    n_datasets: int = 28
    n_targets: int = 50
    n_reports: int = 100
    taus: tuple[float, ...] = parse_taus("-9:3:0.25")
    """The τ grid: wider than the paper's -3..3, whose lower edge is the best τ of dense data sets (docs/experiment.md)."""
    alphas: tuple[float, ...] = ALPHAS
    hybrid: bool = True
    handset: bool = True
    other_region: bool = True
    exact_s: bool = True
    """Also run every prior with the exact eq. 16 S under N_T ~ Poisson(n_targets) (no τ)."""
    batch: bool = False
    """Also run batch TT with the learned prior (label "TT batch": the MAP partition searched from greedy's,
    :class:`tracker.association.batch.BatchAssociator`)."""
    base_seed: int = 0
    gospa_c_m: float = 500.0
    sensor: AirborneSensor = field(default_factory=AirborneSensor)
    integrator: str = "scalespace"

    def __post_init__(self) -> None:
        if not self.block_m > 0:
            raise ValueError(f"block_m must be positive metres, got {self.block_m}")
        if self.n_folds < 2:
            raise ValueError(f"n_folds must be >= 2 (training and held-out blocks), got {self.n_folds}")
        if self.n_datasets < 2:
            raise ValueError(f"n_datasets must be >= 2 (Appendix B needs a sample variance), got {self.n_datasets}")
        if any(not (np.isfinite(a) and a >= 0) for a in self.alphas):
            raise ValueError(f"alphas must be finite and >= 0, got {self.alphas}")

    def experiment(self) -> ExperimentConfig:
        """The per-data-set settings :func:`tracker.study.experiment.run_dataset` reads (region: the cut prior)."""
        return ExperimentConfig(
            n_datasets=self.n_datasets, n_reports=self.n_reports, taus=self.taus, variants=LEARNED,
            n_targets=self.n_targets, region_m=None, keep_fraction=0.5, base_seed=self.base_seed,
            gospa_c_m=self.gospa_c_m, sensor=self.sensor, poisson_mu=float(self.n_targets) if self.exact_s else None,
            integrator=self.integrator, targets_file=self.targets_file, targets_layer=self.targets_layer,
        )


@dataclass(frozen=True)
class Block:
    """A held-out block: its fold, its (col, row) index from the grid's lower-left corner, its window
    (xmin, ymin, xmax, ymax) and how many target locations it holds."""

    fold: int
    index: tuple[int, int]
    window: tuple[float, float, float, float]
    n_points: int

    @property
    def name(self) -> str:
        return f"f{self.fold}_b{self.index[0]}_{self.index[1]}"


@dataclass
class Prepared:
    """The learning pass: per block the cut prior files, by prior label; the fitted models per fold."""

    blocks: list[Block]
    priors: dict[str, dict[str, str]]
    """block name -> prior label ("learned", "hybrid", "handset", "alpha0.5", "other") -> GeoTIFF path."""
    models: dict[int, dict]
    """fold -> {"n_train": points learned from, "likelihoods": the terrain fit's tables, "other_fold": ...}."""
    points: np.ndarray
    fold_of_point: np.ndarray


def alpha_label(alpha: float) -> str:
    return "learned" if alpha == 1.0 else f"alpha{alpha:g}"


def _blocks(points: np.ndarray, origin: tuple[float, float], block_m: float, folds: np.ndarray) -> list[Block]:
    """Every block holding points, with the fold its points were dealt to."""
    ij = np.floor((points - np.asarray(origin)) / block_m).astype(np.int64)
    keys, first, counts = np.unique(ij, axis=0, return_index=True, return_counts=True)
    out = []
    for (i, j), f, n in zip(keys.tolist(), first.tolist(), counts.tolist(), strict=True):
        x0, y0 = origin[0] + i * block_m, origin[1] + j * block_m
        out.append(Block(int(folds[f]), (i, j), (x0, y0, x0 + block_m, y0 + block_m), int(n)))
    return out


def _cut(r: np.ndarray, grid, block: Block, block_m: float) -> tuple[np.ndarray, object]:
    """``r`` (H, W) on the square of side 2·block_m centred on the block (zero beyond the grid) and its grid."""
    cells = int(round(2 * block_m / grid.dx))
    x0 = block.window[0] - 0.5 * block_m
    y1 = block.window[3] + 0.5 * block_m
    col = int(round((x0 - grid.transform.c) / grid.dx))
    row = int(round((grid.transform.f - y1) / grid.dy))
    out = np.zeros((cells, cells))
    r0, r1 = max(row, 0), min(row + cells, grid.height)
    c0, c1 = max(col, 0), min(col + cells, grid.width)
    if r0 < r1 and c0 < c1:
        out[r0 - row:r1 - row, c0 - col:c1 - col] = r[r0:r1, c0:c1]
    return out, grid.window_grid(row, col, cells, cells)


def _far_fold(points: np.ndarray, folds: np.ndarray, fold: int) -> int:
    """The other fold whose points' centroid lies furthest from this fold's."""
    centres = {f: points[folds == f].mean(axis=0) for f in np.unique(folds).tolist()}
    return max((f for f in centres if f != fold), key=lambda f: float(np.hypot(*(centres[f] - centres[fold]))))


def prepare(config: HeldoutConfig, out_dir: str | os.PathLike, progress: bool = True) -> Prepared:
    """The learning pass: fit per fold on the training blocks' points, cut each prior around every
    held-out block with at least ``n_targets`` locations, write the cuts under ``out_dir``."""
    from sklearn.base import clone

    from pipeline.learn import block_folds
    from pipeline.learn.run import fit_hybrid, learning_inputs

    region, lc, points, est = learning_inputs(config.region, config.targets_file, config.targets_layer, progress)
    grid = est.features.grid
    origin = grid.bounds[:2]
    if abs(config.block_m / grid.dx - round(config.block_m / grid.dx)) > 1e-9:
        raise ValueError(f"block_m {config.block_m:g} must be a whole number of {grid.dx:g} m cells")
    folds = block_folds(points, origin, config.block_m, config.n_folds)
    blocks = [b for b in _blocks(points, origin, config.block_m, folds) if b.n_points >= config.n_targets]
    if not blocks:
        raise ValueError(f"{config.targets_file}: no {config.block_m:g} m block holds {config.n_targets} targets (--targets); "
                         "lower --targets or raise --block-m")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    handset = region.model.evaluate(est.features) if config.handset and region.model is not None else None
    fits: dict[int, tuple] = {}
    fold_ids = sorted({b.fold for b in blocks})
    for f in tqdm(fold_ids, desc="learning folds", unit="fold", disable=not progress):
        train = points[folds != f]
        terrain = clone(est).fit(train)
        fits[f] = (terrain, fit_hybrid(terrain, train, lc) if config.hybrid else None, len(train))
    priors: dict[str, dict[str, str]] = {}
    models: dict[int, dict] = {}
    for f in fold_ids:
        terrain, hyb, n_train = fits[f]
        arrays: dict[str, np.ndarray] = {"learned": terrain.prior_.density}
        if hyb is not None:
            arrays["hybrid"] = hyb.prior_.density
        if handset is not None:
            arrays["handset"] = handset
        models[f] = {"n_train": n_train, "likelihoods": terrain.likelihoods_}
        if config.other_region:
            far = _far_fold(points, folds, f)
            # Learned on the far fold's points alone: another region's targets on this region's features.
            arrays["other"] = clone(est).fit(points[folds == far]).prior_.density
            models[f]["other_fold"] = far
        for b in (b for b in blocks if b.fold == f):
            paths = priors[b.name] = {}
            for label, r in arrays.items():
                cut, g = _cut(r, grid, b, config.block_m)
                paths[label] = str(TerrainPrior.from_array(cut, g, {"heldout": label, "block": b.name}).write(
                    out / f"{b.name}_{label}.tif"))
            learned_cut, g = _cut(arrays["learned"], grid, b, config.block_m)
            for a in config.alphas:
                if a != 1.0:
                    paths[alpha_label(a)] = str(TerrainPrior.from_array(learned_cut ** a, g, {"heldout": alpha_label(a)})
                                                .write(out / f"{b.name}_{alpha_label(a)}.tif"))
    return Prepared(blocks, priors, models, points, folds)


def datasets(prepared: Prepared, config: HeldoutConfig) -> list[tuple[int, Block]]:
    """(seed, block) of every data set: blocks taken in turn, seeds base_seed, base_seed + 1, ..."""
    blocks = prepared.blocks
    return [(config.base_seed + i, blocks[i % len(blocks)]) for i in range(config.n_datasets)]


def run_one(task: int, tasks: Sequence[tuple[int, Block]], priors: dict[str, dict[str, str]], config: HeldoutConfig) -> list[dict]:
    """All priors on data set ``task``: records of :func:`run_dataset` with ``label`` (the algorithm, and
    the prior unless learned: "TT", "TT batch", "TT-hybrid"), ``prior``, ``block`` and ``fold`` added."""
    seed, block = tasks[task]
    exp = config.experiment()
    rows = []
    for prior, path in priors[block.name].items():
        runs = [dataclasses.replace(exp, variants=LEARNED if prior == "learned" else ("TT",))]
        if prior == "learned" and config.batch:
            runs.append(dataclasses.replace(exp, variants=("TT",), methods=("batch",)))
        for run in runs:
            for rec in run_dataset(path, seed, run):
                label = rec["algorithm"] if prior == "learned" else f"TT-{prior}"
                rows.append(rec | {"label": label, "prior": prior, "block": block.name, "fold": block.fold})
    return rows


def run_heldout(config: HeldoutConfig, prepared: Prepared, workers: int | None = None, progress: bool = True) -> pd.DataFrame:
    """Every data set and prior as one long table (like :func:`tracker.study.experiment.run_experiment`)."""
    tasks = datasets(prepared, config)
    fn = partial(run_one, tasks=tasks, priors=prepared.priors, config=config)
    rows: list[dict] = []
    bar = tqdm(total=len(tasks), desc="data sets", unit="set", disable=not progress)
    for records in map_local(fn, list(range(len(tasks))), workers):
        rows.extend(records)
        bar.update(1)
    bar.close()
    return pd.DataFrame(rows).sort_values(["seed", "label", "tau"], kind="stable").reset_index(drop=True)


def _matrix(results: pd.DataFrame, label: str, column: str) -> np.ndarray:
    """(data sets, τ) of one label's ``column`` over the exp-S rows, signed so that lower is better."""
    r = results[(results["label"] == label) & (results["s_model"] == "exp")]
    return METRICS[column] * r.pivot(index="seed", columns="tau", values=column).sort_index().sort_index(axis=1).to_numpy()


def _exact(results: pd.DataFrame, label: str, column: str) -> np.ndarray:
    """(data sets, 1) of one label's exact-S ``column``, signed so that lower is better."""
    r = results[(results["label"] == label) & (results["s_model"] == "poisson")].sort_values("seed")
    return METRICS[column] * r[column].to_numpy()[:, None]


def _at_best(results: pd.DataFrame, label: str, metric: str) -> tuple[np.ndarray, int]:
    """(data sets,) of one label's signed ``metric`` at its best τ (chosen by :data:`TAU_BY`), and that τ's index."""
    b = best_tau_index(_matrix(results, label, TAU_BY.get(metric, metric)))
    return _matrix(results, label, metric)[:, b], b


def _p(a: np.ndarray, b: np.ndarray, form: str) -> float | None:
    """P(a better than b) from paired signed values (Appendix B, :func:`~tracker.study.compare.prob_better`);
    None when a metric is undefined on some data set (an RMS error without any estimate within the cut-off)."""
    return prob_better(a - b, form) if np.isfinite(a).all() and np.isfinite(b).all() else None


def summarise_heldout(results: pd.DataFrame, config: HeldoutConfig, prepared: Prepared | None = None) -> dict:
    """Per label and metric the best τ and its mean; P(TT beats UU / UT) in normal and t forms, each at its
    best τ and with the exact S; the α sweep against UU and the largest misspecification TT still wins at."""
    labels = sorted(results["label"].unique(), key=lambda s: (s not in LEARNED, LEARNED.index(s) if s in LEARNED else 0, s))
    taus = sorted(results.loc[results["s_model"] == "exp", "tau"].unique())
    exact = bool((results["s_model"] == "poisson").any())
    per: dict = {}
    for lab in labels:
        per[lab] = {}
        for m, sign in METRICS.items():
            if m == "score" and lab not in LEARNED + BATCH:
                continue
            s = _matrix(results, lab, m)
            at, b = _at_best(results, lab, m)
            per[lab][m] = {"best_tau": float(taus[b]), "tau_chosen_by": TAU_BY.get(m, m),
                           "mean_at_best_tau": float(sign * at.mean()), "mean_by_tau": (sign * s.mean(axis=0)).tolist()}
            if exact:
                per[lab][m]["mean_exact_s"] = float(sign * _exact(results, lab, m).mean())
    table: dict = {}
    for m in METRICS:
        extra = [("TT batch", "TT")] if "TT batch" in labels else []
        for a, b in [("TT", "UU"), ("TT", "UT"), ("UT", "UU")] + extra + [(lab, "UU") for lab in labels if lab not in LEARNED]:
            if m == "score" and a not in LEARNED + BATCH:
                continue
            key = f"{a} vs {b}"
            entry = {form: _p(_at_best(results, a, m)[0], _at_best(results, b, m)[0], form) for form in ("normal", "t")}
            if exact:
                entry |= {f"{form}_exact_s": _p(_exact(results, a, m)[:, 0], _exact(results, b, m)[:, 0], form)
                          for form in ("normal", "t")}
            table.setdefault(m, {})[key] = entry
    sweep = {}
    for a in config.alphas:
        lab = "TT" if a == 1.0 else f"TT-{alpha_label(a)}"
        if lab in per:
            sweep[f"{a:g}"] = {m: {"mean": per[lab][m]["mean_at_best_tau"], "p_beats_uu": table[m][f"{lab} vs UU"]["t"]}
                               for m in HEADLINE}
    wins = [float(a) for a, d in sweep.items() if all(d[m]["p_beats_uu"] >= 0.95 for m in HEADLINE)]
    out = {
        "config": dataclasses.asdict(config),
        "n_datasets": int(results["seed"].nunique()),
        "blocks": sorted(results["block"].unique().tolist()),
        "taus": [float(t) for t in taus],
        "mean_targets_in_window": float(results.groupby("seed")["n_targets"].first().mean()),
        "mean_nd": float(results.groupby("seed")["nd"].first().mean()),
        "labels": per,
        "table": table,
        "alpha_sweep": sweep,
        "alphas_where_tt_beats_uu": wins,
        "largest_misspecification_tt_beats_uu": _largest_misspecification(wins),
        "score_is_proxy": "Score (eq. 18) is against the perfect association under the learned prior (the real "
                          "targets' prior is unknown); compared only among UU, UT, TT and TT batch",
    }
    if prepared is not None:
        out["folds"] = {str(k): v for k, v in prepared.models.items()}
    return out


def _largest_misspecification(alphas: list[float]) -> dict | None:
    """Of the α values at which TT beats UU, the furthest below and above the learned α = 1 (None if none)."""
    if not alphas:
        return None
    return {"weakest_alpha": min(alphas), "strongest_alpha": max(alphas)}


def comparison_markdown(summary: dict, metrics: Sequence[str] = HEADLINE) -> str:
    """The comparison table: per pair, P(first better) in t form at the best τ, and with the exact S."""
    lines = ["| comparison | " + " | ".join(f"{m} (best τ) | {m} (exact S)" for m in metrics) + " |",
             "|---|" + "---|---|" * len(metrics)]
    for key in summary["table"][metrics[0]]:
        cells = []
        for m in metrics:
            e = summary["table"][m].get(key, {})
            cells += [f"{e['t']:.3f}" if "t" in e else "", f"{e['t_exact_s']:.3f}" if "t_exact_s" in e else ""]
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    means = ["", "| prior/variant | " + " | ".join(f"mean {m} (best τ)" for m in metrics) + " |",
             "|---|" + "---|" * len(metrics)]
    for lab, d in summary["labels"].items():
        means.append(f"| {lab} | " + " | ".join(f"{d[m]['mean_at_best_tau']:.3f} (τ {d[m]['best_tau']:+.2f})" for m in metrics) + " |")
    return "\n".join(lines + means)


def alpha_figure(summary: dict, path: str | os.PathLike) -> Path:
    """GOSPA and purity at the best τ against α, with UU's and the learned TT's levels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sweep = summary["alpha_sweep"]
    alphas = [float(a) for a in sweep]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for ax, m, unit in zip(axes, HEADLINE, ("GOSPA (m)", "purity"), strict=True):
        ax.plot(alphas, [sweep[a][m]["mean"] for a in sweep], "o-", label="TT with r^α")
        ax.axhline(summary["labels"]["UU"][m]["mean_at_best_tau"], color="grey", ls="--", label="UU")
        for a in sweep:
            if sweep[a][m]["p_beats_uu"] >= 0.95:
                ax.plot(float(a), sweep[a][m]["mean"], "k*", ms=10)
        ax.set_xlabel("α (1 = learned)")
        ax.set_ylabel(unit)
        ax.set_title(f"{m} at the {'best-GOSPA' if m in TAU_BY else 'best'} τ (★: beats UU, P ≥ .95)", fontsize=9)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    with atomic_paths(path) as (tmp,):
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path


def write_heldout(results: pd.DataFrame, summary: dict, out_dir: str | os.PathLike) -> dict[str, str]:
    """results.parquet (CSV without pyarrow), summary.json, table.md and alpha.png in ``out_dir``."""
    out = Path(out_dir)
    paths = {"results": write_results(results, out)}
    with atomic_paths(out / "summary.json") as (tmp,):
        tmp.write_text(json.dumps(summary, indent=1, default=float))
    paths["summary"] = str(out / "summary.json")
    with atomic_paths(out / "table.md") as (tmp,):
        tmp.write_text("P(first better than second), t form, Appendix B; each at its best τ and with the exact S:\n\n"
                       + comparison_markdown(summary) + "\n")
    paths["table"] = str(out / "table.md")
    if summary["alpha_sweep"] and "UU" in summary["labels"]:
        paths["alpha_figure"] = str(alpha_figure(summary, out / "alpha.png"))
    return paths


def run_and_write_heldout(config: HeldoutConfig, out_dir: str | os.PathLike, workers: int | None = None,
                          progress: bool = True) -> tuple[dict, dict]:
    """The ``terrain-track heldout`` command: learn per fold, track every prior, summarise, write."""
    out = Path(out_dir)
    prepared = prepare(config, out / "priors", progress)
    results = run_heldout(config, prepared, workers, progress)
    summary = summarise_heldout(results, config, prepared)
    return summary, write_heldout(results, summary, out)


def regime_table(config: HeldoutConfig, prepared: Prepared, n_targets: Sequence[int], azimuth_mrad: Sequence[float],
                 workers: int | None = None, progress: bool = True) -> pd.DataFrame:
    """Where the learned prior pays off: per target count (targets per held-out block, i.e. density) and sensor
    azimuth noise (mrad), UU, UT and TT with the learned prior on ``config.n_datasets`` data sets; one row
    with the mean GOSPA and purity of each at its best τ and P(TT beats UU), t form, on each metric.
    Blocks with fewer locations than the target count are left out (counted in ``blocks``)."""
    rows = []
    learned_only = {name: {"learned": paths["learned"]} for name, paths in prepared.priors.items()}
    for n in n_targets:
        blocks = [b for b in prepared.blocks if b.n_points >= n]
        if not blocks:
            continue
        for az in azimuth_mrad:
            cfg = dataclasses.replace(config, n_targets=int(n), exact_s=False,
                                      sensor=dataclasses.replace(config.sensor, azimuth_std_rad=az / 1000.0))
            sub = dataclasses.replace(prepared, blocks=blocks, priors=learned_only)
            res = run_heldout(cfg, sub, workers, progress)
            row = {"n_targets": int(n), "azimuth_mrad": float(az), "blocks": len(blocks), "n_datasets": cfg.n_datasets,
                   "density_per_km2": float(n / (config.block_m / 1000.0) ** 2)}
            for m in HEADLINE:
                for lab in LEARNED:
                    row[f"{lab}_{m}"] = float(METRICS[m] * _at_best(res, lab, m)[0].mean())
                row[f"p_tt_beats_uu_{m}"] = _p(_at_best(res, "TT", m)[0], _at_best(res, "UU", m)[0], "t")
            rows.append(row)
    return pd.DataFrame(rows)
