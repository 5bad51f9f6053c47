"""The paper's experiment (paper 1, section 6): UU, UT and TT over a τ grid on seeded data sets.

``run_dataset(prior_path, seed, config)`` is a pure function (one data set in, a list of flat
records out) so it maps onto any executor: a local process pool by default (``run_experiment``),
or Dask. Per data set it simulates the scenario, runs the association for every variant and τ,
and scores every result against the perfect-association estimate with one shared Gram matrix:
mixture components are keyed by the set of reports they fuse, and a component with the same
report set is the same density in every τ, in UT and TT, and in the perfect estimate — so each
distinct pair integral is computed once per data set, however many τ values and variants use it.

Outputs (``write_outputs``): ``results.parquet`` (or CSV), ``summary.json`` (mean/std per variant
and τ, best τ, Table 1 in normal and t forms next to the paper's), and PNG figures like 11–15.
"""

from __future__ import annotations

import json
import multiprocessing
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache, partial
from pathlib import Path

import numba
import numpy as np
import pandas as pd
from affine import Affine
from tqdm.auto import tqdm

from common.atomic import atomic_paths
from pipeline.prior import TerrainPrior
from tracker.association.batch import BatchAssociator, batch_estimate, log_posterior
from tracker.association.greedy import associate, perfect_estimate
from tracker.integrate import METHODS as INTEGRATORS
from tracker.integrate import Integrator, integrate_checked
from tracker.models.sfunc import ExpS, PoissonS, SModel
from tracker.study.compare import best_tau_index, compare, comparison_table, prob_better
from tracker.study.metrics import ScoreGram, gospa, mixture_weights, ospa, posterior_means, purity
from tracker.study.plots import PAPER_TABLE, table_markdown, write_figures
from tracker.study.simulate import (
    AirborneSensor,
    central_windows,
    file_targets,
    simulate,
    simulate_points,
)
from tracker.types import Estimate, Reports

VARIANTS = ("UU", "UT", "TT")
METHODS = ("greedy", "batch", "posterior")
"""Association methods: paper 1's greedy tracker; batch, the MAP search started from it; posterior,
batch's Bayes estimates from a posterior sample started at the MAP (the posterior-mean mixture for
the Score, the posterior median of N_D)."""


def parse_taus(spec: str) -> tuple[float, ...]:
    """``"start:stop:step"`` (stop included, like the paper's -3..3 by .25 = 25 values) or a comma list."""
    try:
        if ":" in spec:
            start, stop, step = (float(s) for s in spec.split(":"))
            if not step > 0 or stop < start:
                raise ValueError
            n = int(np.floor((stop - start) / step + 1e-9)) + 1
            return tuple(float(round(start + i * step, 12)) for i in range(n))
        return tuple(float(s) for s in spec.split(","))
    except ValueError:
        raise ValueError(f"--tau {spec!r}: expected start:stop:step with step > 0 and stop >= start, or a comma list") from None


@dataclass(frozen=True)
class ExperimentConfig:
    """Everything that defines the experiment besides the prior (seeds are base_seed + data set index)."""

    n_datasets: int = 28
    n_reports: int = 100
    taus: tuple[float, ...] = parse_taus("-3:3:0.25")
    variants: tuple[str, ...] = VARIANTS
    n_targets: int = 200
    region_m: float | None = 14000.0
    keep_fraction: float = 0.5
    base_seed: int = 0
    gospa_c_m: float = 500.0
    sensor: AirborneSensor = field(default_factory=AirborneSensor)
    poisson_mu: float | None = None
    """Also run each variant with the exact eq. 16 S(n, k) under N_T ~ Poisson(mu) (no τ)."""
    integrator: str = "scalespace"
    """``method`` of :func:`tracker.integrate.integrate`: "scalespace" or "terraces"."""
    targets_file: str | None = None
    """Pick each data set's ``n_targets`` among this vector file's locations in the window
    (:func:`~tracker.study.simulate.simulate_points`) instead of drawing them from the prior."""
    targets_layer: str | None = None
    methods: tuple[str, ...] = ("greedy",)
    """Association methods (:data:`METHODS`); batch is the MAP search from greedy's partition, with
    ``batch_anneal`` annealed sweeps per restart and ``batch_restarts`` restarts from singletons."""
    batch_anneal: int = 10
    batch_restarts: int = 1
    batch_window: bool = True
    """Batch associates under the design's own model: r restricted to the central keep window and
    renormalised (:func:`window_prior`; UU: uniform over the window), where the design puts every
    target. Greedy keeps r over the whole grid, as in the paper."""
    batch_nd_samples: int = 100
    """The posterior sample of batch's model: ``batch_nd_burn_in`` + ``batch_nd_samples`` sampling
    sweeps started at the MAP partition. The posterior method estimates from it at every S. For the
    batch method, with the exact S, N̂_D is its posterior median of N_D (the Bayes estimate under
    |N̂_D − N_D|, :func:`add_batch_nd`); at a τ batch's N̂_D is the MAP partition's cluster count, like
    greedy's. 0: no sampling for the batch method (the MAP count everywhere); the posterior method
    needs at least 1."""
    batch_nd_burn_in: int = 10

    def __post_init__(self) -> None:
        bad = [v for v in self.variants if v not in VARIANTS]
        if bad:
            raise ValueError(f"variants {bad} unknown; choose from {VARIANTS}")
        if self.n_datasets < 2:
            raise ValueError(f"n_datasets must be >= 2 (Appendix B needs a sample variance), got {self.n_datasets}")
        if not self.taus:
            raise ValueError("taus must not be empty")
        if self.poisson_mu is not None:
            PoissonS(self.poisson_mu)  # validates mu
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator {self.integrator!r} unknown; choose from {INTEGRATORS}")
        bad = [m for m in self.methods if m not in METHODS]
        if bad or not self.methods:
            raise ValueError(f"methods {bad or '(none)'} unknown; choose from {METHODS}")
        if "posterior" in self.methods and self.batch_nd_samples < 1:
            raise ValueError(f"methods posterior needs batch_nd_samples >= 1, got {self.batch_nd_samples}")

    @property
    def seeds(self) -> list[int]:
        return [self.base_seed + i for i in range(self.n_datasets)]


def _load_prior(prior_path: str) -> TerrainPrior:
    """The prior, read once per process and file version (a rebuilt file at the same path is re-read)."""
    try:
        st = os.stat(prior_path)
    except FileNotFoundError:
        return TerrainPrior.read(prior_path)  # raises the PriorError naming the missing file
    return _read_prior(prior_path, st.st_ino, st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=4)
def _read_prior(prior_path: str, inode: int, mtime_ns: int, size: int) -> TerrainPrior:
    # The summed-area tables are memory-mapped; inode, mtime and size only key the cache (an atomic
    # rewrite replaces the inode).
    return TerrainPrior.read(prior_path)


def window_mask(prior: TerrainPrior, bounds: tuple[float, float, float, float]) -> np.ndarray:
    """(H, W) cells whose centres lie in ``bounds`` (xmin, ymin, xmax, ymax metres)."""
    g = prior.grid
    x = g.transform.c + (np.arange(g.width) + 0.5) * g.dx
    y = g.transform.f - (np.arange(g.height) + 0.5) * g.dy
    return ((y >= bounds[1]) & (y < bounds[3]))[:, None] & ((x >= bounds[0]) & (x < bounds[2]))[None, :]


def window_prior(prior: TerrainPrior, bounds: tuple[float, float, float, float]) -> TerrainPrior:
    """r restricted to the cells of ``bounds`` and renormalised (per m²), on the sub-grid of those cells:
    the target density of the central-window design. Its grid is the window, so UU's u = 1 / window area."""
    mask = window_mask(prior, bounds)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not rows.size:
        raise ValueError(f"window {bounds} holds no cell centre of the grid {prior.grid.bounds}")
    g = prior.grid
    grid = replace(g, transform=g.transform @ Affine.translation(int(cols[0]), int(rows[0])), height=rows.size, width=cols.size)
    r = prior.density[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    return TerrainPrior.from_array(r, grid, {**prior.model, "window": [float(b) for b in bounds]})


def expected_in_window(prior: TerrainPrior, n_targets: int, region_m: float | None = 14000.0,
                       keep_fraction: float = 0.5) -> float:
    """μ: the expected number of the paper's ``n_targets`` (drawn over the region) that fall in the
    central window, n_targets × mass(window) / mass(region)."""
    region, keep = central_windows(prior, region_m, keep_fraction)
    return n_targets * float(prior.density[window_mask(prior, keep)].sum()) / float(prior.density[window_mask(prior, region)].sum())


def _load_window_prior(prior_path: str, region_m: float | None, keep_fraction: float) -> TerrainPrior:
    """:func:`window_prior` of the design's keep window, built once per process and prior file version."""
    prior = _load_prior(prior_path)
    return _window_of(prior, region_m, keep_fraction)


@lru_cache(maxsize=4)
def _window_of(prior: TerrainPrior, region_m: float | None, keep_fraction: float) -> TerrainPrior:
    # keyed by the cached prior object, which _read_prior renews when the file changes
    return window_prior(prior, central_windows(prior, region_m, keep_fraction)[1])


class CachedIntegrator:
    """Memoises an :class:`~tracker.integrate.Integrator` per exact (mean, covariance) bytes for one prior.

    Across τ values (and between UT, TT and the scoring of one data set) the tracker integrates the
    same Gaussians again until its decisions diverge: ∫G(z, V) r of every report, and the candidate
    products of identical hypothesis states. Only misses reach the wrapped integrator; ``hits`` and
    ``misses`` count Gaussians.
    """

    def __init__(self, prior: TerrainPrior, integrator: Integrator = integrate_checked) -> None:
        self.prior = prior
        self.integrator = integrator
        self.table: dict[bytes, float] = {}  # ∫G r, keyed by the bytes of (mean, covariance)
        self.table2: dict[bytes, float] = {}  # ∫G r²
        self.hits = 0
        self.misses = 0

    def __call__(self, prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, squared: bool = False) -> np.ndarray:
        if prior is not self.prior:
            raise ValueError("CachedIntegrator: called with a different prior than it caches")
        means = np.asarray(means, dtype=np.float64)
        covs = np.asarray(covs, dtype=np.float64)
        n = means.shape[0]
        if n == 0:  # e.g. the posterior means of a run whose every report fell off the prior
            return np.empty(0)
        table = self.table2 if squared else self.table
        blob = np.concatenate([means.reshape(n, -1), covs.reshape(n, -1)], axis=1).tobytes()
        width = len(blob) // n
        keys = [blob[i * width:(i + 1) * width] for i in range(n)]
        values = [table.get(k) for k in keys]
        miss = [i for i, v in enumerate(values) if v is None]
        self.hits += n - len(miss)
        if miss:
            self.misses += len(miss)
            fresh = np.asarray(self.integrator(prior, means[miss], covs[miss], squared=squared), dtype=np.float64)
            for i, v in zip(miss, fresh.tolist(), strict=True):
                values[i] = table[keys[i]] = v
        return np.array(values, dtype=np.float64)


def member_sets(assignment: np.ndarray, n: int) -> list[bytes]:
    """Per hypothesis 0..n−1, the indices of its reports (``assignment == q``) as ascending int32 bytes."""
    order = np.argsort(assignment, kind="stable")
    bounds = (4 * np.searchsorted(assignment[order], np.arange(n + 1))).tolist()
    blob = order.astype(np.int32).tobytes()  # report indices grouped by hypothesis, 4 bytes each
    return [blob[bounds[q]:bounds[q + 1]] for q in range(n)]


class _Components:
    """Distinct mixture components of one data set, keyed by (fused report set, terrain flag)."""

    def __init__(self) -> None:
        self.index: dict[tuple[bytes, bool], int] = {}
        self.means: list[np.ndarray] = []
        self.covs: list[np.ndarray] = []
        self.terrain: list[bool] = []

    def register(self, assignment: np.ndarray, means: np.ndarray, covs: np.ndarray, terrain: bool) -> np.ndarray:
        """Component indices of hypotheses 0..len(means)-1, whose reports are ``assignment == q``."""
        return self.register_sets(member_sets(assignment, len(means)), means, covs, terrain)

    def register_sets(self, sets: Sequence[bytes], means: np.ndarray, covs: np.ndarray, terrain: bool) -> np.ndarray:
        """Component indices of the clusters whose report indices (ascending int32 bytes) are ``sets``."""
        out = np.empty(len(sets), dtype=np.intp)
        for q, members in enumerate(sets):
            key = (members, terrain)
            idx = self.index.get(key)
            if idx is None:
                idx = self.index[key] = len(self.means)
                self.means.append(means[q])
                self.covs.append(covs[q])
                self.terrain.append(terrain)
            out[q] = idx
        return out

    def gram(self, prior: TerrainPrior, integrator: Integrator, mixtures: Iterable[np.ndarray]) -> ScoreGram:
        """The Gram matrix over the pairs that occur together in one of ``mixtures`` (component indices)."""
        n = len(self.means)
        needed = np.zeros((n, n), dtype=bool)
        for members in mixtures:
            mask = np.zeros(n, dtype=bool)
            mask[members] = True
            needed |= mask[:, None] & mask[None, :]
        return ScoreGram(prior, np.array(self.means), np.array(self.covs), np.array(self.terrain),
                         integrator=integrator, needed=needed)


def _scenario(prior: TerrainPrior, seed: int, config: ExperimentConfig):
    """Data set ``seed`` of the design: targets from the prior (or the targets file), reports."""
    if config.targets_file is None:
        return simulate(prior, seed, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
    locations = file_targets(config.targets_file, config.targets_layer, prior.grid)
    return simulate_points(prior, locations, seed, config.n_targets, config.n_reports, config.region_m,
                           config.keep_fraction, config.sensor, source=config.targets_file)


def _settings(config: ExperimentConfig) -> list[tuple[str, float, SModel]]:
    """(label, τ, S model): the paper's e^{-nτ} per τ, and optionally eq. 16 under Poisson(μ)."""
    settings = [("exp", float(tau), ExpS(float(tau))) for tau in config.taus]
    if config.poisson_mu is not None:
        settings.append(("poisson", float("nan"), PoissonS(config.poisson_mu)))
    return settings


@dataclass
class _Context:
    """One data set's prior, reports and integrators; ``model_prior`` is the one batch associates with."""

    prior: TerrainPrior
    reports: object
    integrator: CachedIntegrator
    model_prior: TerrainPrior
    model_integrator: CachedIntegrator
    config: ExperimentConfig
    seed: int
    runs: dict = field(default_factory=dict)


def _context(prior_path: str, reports, config: ExperimentConfig, integrator: CachedIntegrator, seed: int) -> _Context:
    prior = integrator.prior
    model_prior = prior
    model_integrator = integrator
    if config.batch_window and {"batch", "posterior"} & set(config.methods):
        model_prior = _load_window_prior(prior_path, config.region_m, config.keep_fraction)
        model_integrator = CachedIntegrator(model_prior, partial(integrate_checked, method=config.integrator))
    return _Context(prior, reports, integrator, model_prior, model_integrator, config, seed)


def run_dataset(prior_path: str | os.PathLike, seed: int, config: ExperimentConfig) -> list[dict]:
    """Simulate data set ``seed`` and score every variant at every τ; one record per (variant, τ).

    Record fields: dataset seed, variant, s_model ("exp": S = e^{-nτ}; "poisson": eq. 16 with
    ``config.poisson_mu``, tau NaN), tau, score (per m; the paper plots it ×10^4.5),
    score_error_bound (bound on |Score²| error from skipped negligible pairs, per m²), log_posterior
    (ln p(Λ|Z) + const under the method's associating model: greedy's r over the grid, batch's
    :attr:`ExperimentConfig.batch_window` model) and greedy_log_posterior (greedy's partition under
    that same model), nd_hat (the partition's cluster count), nd, nd_abs_error,
    gospa_m and ospa_m (metres, cut-off ``gospa_c_m``; points are the estimate's means:
    the Gaussians' for UU, the terrain posteriors' for UT and TT), rms_error_m (root mean square distance
    of the posterior means to their detected targets in GOSPA's assignment, pairs closer than the cut-off),
    purity, skipped (reports off the prior, left unassigned), n_targets (kept targets in the window).
    """
    prior = _load_prior(str(prior_path))
    sc = _scenario(prior, seed, config)
    reports = sc.reports
    integrator = CachedIntegrator(prior, partial(integrate_checked, method=config.integrator))
    ctx = _context(str(prior_path), reports, config, integrator, seed)
    comps = _Components()
    perfect = perfect_estimate(prior, reports, terrain=True, integrator=integrator)
    ref = comps.register(np.searchsorted(perfect.labels, reports.truth), perfect.means, perfect.covs, True)
    detected = sc.targets[perfect.labels]
    nd = len(ref)

    evaluations = []
    for variant in config.variants:
        # UT associates exactly as UU (paper sec. 6); only its reported estimate differs.
        assoc_variant = "UU" if variant == "UT" else variant
        for label, tau, s_model in _settings(config):
            for method in config.methods:
                res = _run(ctx, method, assoc_variant, s_model)
                est = res.estimate
                terrain = variant != "UU"
                members = comps.register(res.assignments, est.means, est.covs, terrain)
                scored = (members, None)  # the partition's equally weighted mixture
                if res.mixture is not None:
                    sets, means, covs, weights = res.mixture
                    scored = (comps.register_sets(sets, means, covs, terrain), weights)
                evaluations.append((variant, method, label, tau, res, members, scored))

    gram = comps.gram(prior, integrator, (np.concatenate([scored[0], ref]) for *_, scored in evaluations))
    n = len(comps.means)
    w_ref = mixture_weights(n, ref, -1.0)
    # Point estimates for GOSPA/OSPA: each component's mean (the terrain posterior's for UT/TT).
    points = np.array(comps.means)
    terrain = np.array(comps.terrain)
    points[terrain] = posterior_means(prior, points[terrain], np.array(comps.covs)[terrain], integrator=integrator)
    records = []
    # Point metrics once per distinct (association, estimate kind): τ runs often agree.
    assoc_metrics: dict[tuple[bytes, bool], dict] = {}
    for variant, method, label, tau, res, members, (scored, weights) in evaluations:
        w = mixture_weights(n, scored) if weights is None else np.bincount(scored, weights, minlength=n)
        s, err = gram.score(w + w_ref)
        key = (res.assignments.tobytes(), variant != "UU")
        if key not in assoc_metrics:
            on = res.assignments >= 0
            g = gospa(points[members], detected, config.gospa_c_m)
            assigned = len(detected) - g["missed"]
            assoc_metrics[key] = {
                "gospa_m": g["gospa"],
                "rms_error_m": float(np.sqrt(g["localisation"] / assigned)) if assigned else float("nan"),
                "ospa_m": ospa(points[members], detected, config.gospa_c_m),
                "purity": purity(res.assignments[on], reports.truth[on]),
                "skipped": int((~on).sum()),
            }
        records.append({
            "seed": int(seed), "variant": variant, "method": method, "algorithm": algorithm_name(variant, method),
            "s_model": label, "tau": tau, "score": s, "score_error_bound": err, "log_posterior": res.log_posterior,
            "greedy_log_posterior": res.greedy_log_posterior,
            "nd_hat": int(res.n_detected), "nd": nd, "nd_abs_error": abs(int(res.n_detected) - nd),
            **assoc_metrics[key], "n_targets": int(len(sc.targets)),
        })
    return records


def algorithm_name(variant: str, method: str) -> str:
    """The results' ``algorithm`` column: the variant for greedy ("TT"), "TT batch" for batch."""
    return variant if method == "greedy" else f"{variant} {method}"


@dataclass(frozen=True)
class _Run:
    """One association of a data set: ``assignments`` (K,) (−1: skipped), the fused Gaussians
    ``estimate`` (row q = hypothesis q), its N̂_D, ln p(Λ|Z) + const under the associating model, and that
    of greedy's partition under the same model. ``mixture`` (the posterior method): the scored estimate
    instead of the partition's, as (member sets, fused means, covariances, weights)."""

    assignments: np.ndarray
    estimate: object
    n_detected: int
    log_posterior: float
    greedy_log_posterior: float
    mixture: tuple | None = None


def _run(ctx: _Context, method: str, variant: str, s_model: SModel) -> _Run:
    """The (memoised) association of the reports by ``method``. Batch starts from greedy's partition of
    the reports greedy kept on the prior that also have mass under batch's model."""
    key = (method, variant, s_model)
    if key in ctx.runs:
        return ctx.runs[key]
    reports = ctx.reports
    if method == "greedy":
        res = associate(ctx.prior, reports, variant, s_model=s_model, off_prior="skip", integrator=ctx.integrator)
        on = res.assignments >= 0
        lp = log_posterior(ctx.prior, reports.subset(np.flatnonzero(on)), res.assignments[on], s_model, variant, ctx.integrator)
        ctx.runs[key] = _Run(res.assignments, res.estimate, int(res.n_detected), lp, lp)
        return ctx.runs[key]
    if method == "posterior":
        mapped = _run(ctx, "batch", variant, s_model)
        kept = np.flatnonzero(mapped.assignments >= 0)
        sample = _posterior_sample(ctx, variant, s_model)
        sets, weights = posterior_mixture(sample.samples, kept, len(reports))
        fused = fuse_sets(ctx.prior, reports, sets)
        ctx.runs[key] = _Run(mapped.assignments, mapped.estimate, posterior_median(sample.nd_values, sample.nd_prob),
                             mapped.log_posterior, mapped.greedy_log_posterior, (sets, fused.means, fused.covs, weights))
        return ctx.runs[key]
    greedy = _run(ctx, "greedy", variant, s_model)
    kept, init = _batch_start(ctx, greedy.assignments, variant)
    sub = reports.subset(kept)
    res = BatchAssociator(ctx.model_prior, variant, s_model=s_model, anneal=ctx.config.batch_anneal,
                          restarts=ctx.config.batch_restarts, seed=0, integrator=ctx.model_integrator).fit(sub, init=init)
    assignments = np.full(len(reports), -1, np.int64)
    assignments[kept] = res.labels
    # the Gaussian parts only: a component's terrain flag applies r when it is scored
    est = batch_estimate(ctx.prior, sub, res.labels, "UU", ctx.integrator)
    ctx.runs[key] = _Run(assignments, est, res.n_detected, res.log_posterior, res.greedy_log_posterior)
    return ctx.runs[key]


def _posterior_sample(ctx: _Context, variant: str, s_model: SModel):
    """The (memoised) posterior sample under batch's model: ``batch_nd_burn_in`` + ``batch_nd_samples``
    sampling sweeps (one split–merge proposal each, seeded by the data set) from the MAP partition."""
    key = ("sample", variant, s_model)
    if key not in ctx.runs:
        mapped = _run(ctx, "batch", variant, s_model)
        kept = np.flatnonzero(mapped.assignments >= 0)
        config = ctx.config
        ctx.runs[key] = BatchAssociator(
            ctx.model_prior, variant, s_model=s_model, mode="sample", burn_in=config.batch_nd_burn_in,
            samples=config.batch_nd_samples, split_merge=1, seed=ctx.seed, keep_samples=True,
            integrator=ctx.model_integrator).fit(ctx.reports.subset(kept), init=mapped.assignments[kept])
    return ctx.runs[key]


def posterior_mixture(samples: np.ndarray, kept: np.ndarray, n_reports: int) -> tuple[list[bytes], np.ndarray]:
    """The posterior-mean mixture of sampled partitions ``samples`` (S, len(kept)) of the reports
    ``kept`` (ascending indices among ``n_reports``): its distinct clusters as member sets (ascending
    int32 bytes of report indices) and their weights, the mean over samples of 1[C ∈ Λ_s] / n_s."""
    weights: dict[bytes, float] = {}
    full = np.full(n_reports, -1, np.int64)
    for labels in samples:
        full[kept] = np.unique(labels, return_inverse=True)[1]
        n = int(full.max()) + 1
        for members in member_sets(full, n):
            weights[members] = weights.get(members, 0.0) + 1.0 / (n * len(samples))
    return list(weights), np.fromiter(weights.values(), np.float64, len(weights))


def fuse_sets(prior: TerrainPrior, reports: Reports, sets: Sequence[bytes]) -> Estimate:
    """The fused Gaussians (information form, :func:`perfect_estimate`) of possibly overlapping report
    sets ``sets`` (ascending int32 bytes of report indices); row q fuses ``sets[q]``."""
    members = [np.frombuffer(m, np.int32) for m in sets]
    rows = np.concatenate(members)
    group = np.repeat(np.arange(len(sets)), [m.size for m in members])
    stacked = Reports(reports.means[rows], reports.covs[rows], reports.times[rows], group)
    return perfect_estimate(prior, stacked, terrain=False)


def _batch_start(ctx: _Context, greedy_assignments: np.ndarray, variant: str) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the reports batch associates, and greedy's labels of them (0..n−1): greedy's kept
    reports, less (TT) those without mass under the model prior (a report far outside the window)."""
    on = greedy_assignments >= 0
    if variant == "TT" and ctx.model_prior is not ctx.prior:
        r = ctx.reports
        on &= ctx.model_integrator(ctx.model_prior, r.means, r.covs) > 0
    kept = np.flatnonzero(on)
    return kept, np.unique(greedy_assignments[kept], return_inverse=True)[1]


def posterior_median(values: np.ndarray, prob: np.ndarray) -> int:
    """The smallest value whose posterior CDF reaches 1/2 (``values`` ascending)."""
    return int(values[min(int(np.searchsorted(np.cumsum(prob), 0.5 - 1e-12)), len(values) - 1)])


def _batch_dataset(prior_path: str | os.PathLike, seed: int, config: ExperimentConfig) -> tuple:
    """Data set ``seed``'s reports, its association context and its S models keyed by (label, τ or None)."""
    prior = _load_prior(str(prior_path))
    reports = _scenario(prior, seed, config).reports
    ctx = _context(str(prior_path), reports, config, CachedIntegrator(prior, partial(integrate_checked, method=config.integrator)), seed)
    return reports, ctx, {(label, tau if label == "exp" else None): s for label, tau, s in _settings(config)}


def batch_nd(prior_path: str | os.PathLike, seed: int, config: ExperimentConfig,
             wanted: Sequence[tuple[str, str, float | None]]) -> list[dict]:
    """The posterior of N_D for data set ``seed`` under batch's model, per (associating variant,
    s_model label, τ) in ``wanted`` (τ None for "poisson", the experiment's only use), from the posterior
    method's sample (:func:`_posterior_sample`). Records: seed, assoc_variant, s_model, tau (+inf for
    "poisson"), nd_hat_bayes (posterior median), nd_posterior_mean."""
    _, ctx, models = _batch_dataset(prior_path, seed, config)
    out = []
    for variant, label, tau in wanted:
        res = _posterior_sample(ctx, variant, models[(label, tau)])
        out.append({"seed": int(seed), "assoc_variant": variant, "s_model": label, "tau": np.inf if tau is None else tau,
                    "nd_hat_bayes": posterior_median(res.nd_values, res.nd_prob),
                    "nd_posterior_mean": float(res.nd_values @ res.nd_prob)})
    return out


def map_convergence(prior_path: str | os.PathLike, seed: int, config: ExperimentConfig,
                    wanted: Sequence[tuple[str, str, float | None]], anneal: int = 50, restarts: int = 3,
                    split_merge: int = 5) -> list[dict]:
    """The experiment's MAP (:func:`run_dataset`'s batch) against a long search on data set ``seed``, per
    (variant, s_model label, τ) in ``wanted`` (τ None for "poisson"): ``anneal`` annealed sweeps with
    ``split_merge`` proposals each and ICM, from greedy's partition and from all singletons ``restarts``
    times, best state kept. Records: seed, variant, s_model, tau, short_log_posterior, long_log_posterior
    (ln p(Λ|Z) + const under batch's model)."""
    reports, ctx, models = _batch_dataset(prior_path, seed, config)
    out = []
    for variant, label, tau in wanted:
        s_model = models[(label, tau)]
        short = _run(ctx, "batch", variant, s_model)
        kept, init = _batch_start(ctx, _run(ctx, "greedy", variant, s_model).assignments, variant)
        res = BatchAssociator(ctx.model_prior, variant, s_model=s_model, anneal=anneal, restarts=restarts,
                              split_merge=split_merge, seed=seed, integrator=ctx.model_integrator).fit(reports.subset(kept), init=init)
        out.append({"seed": int(seed), "variant": variant, "s_model": label, "tau": np.inf if tau is None else tau,
                    "short_log_posterior": short.log_posterior, "long_log_posterior": res.log_posterior})
    return out


def add_batch_nd(results: pd.DataFrame, prior_path: str | os.PathLike, config: ExperimentConfig,
                 mapper: Callable[[Callable[[int], list[dict]], Sequence[int]], Iterable[list[dict]]]) -> pd.DataFrame:
    """Batch's Bayes N̂_D (:func:`batch_nd`) with the exact S, as columns nd_hat_bayes,
    nd_abs_error_bayes (NaN elsewhere: at a τ batch's N̂_D is its MAP count ``nd_hat``);
    ``mapper(fn, seeds)`` runs the data sets (:func:`map_local`, or Dask)."""
    if "batch" not in config.methods or not config.batch_nd_samples or config.poisson_mu is None:
        return results
    wanted = {("UU" if v == "UT" else v, "poisson", None) for v in config.variants}
    fn = partial(batch_nd, str(prior_path), config=config, wanted=tuple(sorted(wanted, key=str)))
    nd = pd.DataFrame([r for records in mapper(fn, config.seeds) for r in records])
    key = ["seed", "assoc_variant", "s_model", "tau"]  # τ of the exact S: +inf (NaN never matches in a merge)
    left = results.assign(assoc_variant=results["variant"].replace("UT", "UU"), tau=results["tau"].fillna(np.inf))
    merged = left.merge(nd[[*key, "nd_hat_bayes", "nd_posterior_mean"]], on=key, how="left")
    greedy = merged["method"] != "batch"
    merged.loc[greedy, ["nd_hat_bayes", "nd_posterior_mean"]] = np.nan
    merged["nd_abs_error_bayes"] = (merged["nd_hat_bayes"] - merged["nd"]).abs()
    merged["tau"] = results["tau"].to_numpy()
    return merged.drop(columns="assoc_variant")


def _worker_init() -> None:
    # One numba thread per worker process: the pool already uses the cores.
    numba.set_num_threads(1)


def _pool_context() -> multiprocessing.context.BaseContext:
    """Fork while this process has no numba (OpenMP) thread pool yet: safe and instant. Once it has
    one, forking is unsafe, so workers come from a fork server with this module preloaded."""
    try:
        numba.threading_layer()
    except ValueError:
        return multiprocessing.get_context("fork")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload([__name__])
    return ctx


def map_local(fn: Callable[[int], list[dict]], seeds: Sequence[int], workers: int | None) -> Iterable[list[dict]]:
    """Map ``fn`` over seeds in a local process pool (``workers`` processes, default all cores;
    1 runs inline), results in seed order."""
    workers = workers or os.cpu_count() or 1
    if workers == 1 or len(seeds) == 1:
        yield from map(fn, seeds)
        return
    with ProcessPoolExecutor(max_workers=min(workers, len(seeds)), mp_context=_pool_context(), initializer=_worker_init) as pool:
        yield from pool.map(fn, seeds)


def run_experiment(
    prior_path: str | os.PathLike, config: ExperimentConfig, workers: int | None = None, progress: bool = True
) -> pd.DataFrame:
    """All data sets, variants and τ values as one long table (rows sorted by seed, variant, τ), with
    batch's Bayes N̂_D (:func:`add_batch_nd`) when batch runs."""

    def mapper(fn: Callable[[int], list[dict]], seeds: Sequence[int], desc: str = "data sets") -> Iterable[list[dict]]:
        yield from tqdm(map_local(fn, seeds, workers), total=len(seeds), desc=desc, unit="set", disable=not progress)

    rows = [r for records in mapper(partial(run_dataset, str(prior_path), config=config), config.seeds) for r in records]
    results = pd.DataFrame(rows).sort_values(["seed", "method", "variant", "tau"], kind="stable").reset_index(drop=True)
    return add_batch_nd(results, prior_path, config, partial(mapper, desc="batch N_D posterior"))


def score_matrix(results: pd.DataFrame, algorithm: str, column: str = "score") -> np.ndarray:
    """(data sets, τ) array of one algorithm's ``column`` (:func:`algorithm_name`: "TT", "TT batch").
    A table without an ``algorithm`` column holds greedy runs only (results written before
    ``methods``, hand-built tables): there the algorithm is the variant."""
    key = "algorithm" if "algorithm" in results else "variant"
    table = results[results[key] == algorithm].pivot(index="seed", columns="tau", values=column)
    return table.sort_index().sort_index(axis=1).to_numpy()


def summarise(results: pd.DataFrame, config: ExperimentConfig) -> dict:
    """Per-variant curves, best τ, and Table 1 (normal and t forms) beside the paper's values; with
    Poisson rows, each variant's exact-S score and P(exact S better than the best τ)."""
    poisson = results[results["s_model"] == "poisson"]
    results = results[results["s_model"] == "exp"]
    present = set(results["algorithm"])
    variants = [a for m in METHODS for v in VARIANTS if (a := algorithm_name(v, m)) in present]
    taus = sorted(results["tau"].unique())
    per_variant = {}
    scores = {}
    for v in variants:
        s = score_matrix(results, v)
        scores[v] = s
        b = best_tau_index(s)
        nd_err = score_matrix(results, v, "nd_abs_error")
        per_variant[v] = {
            "best_tau": taus[b],
            "best_tau_at_grid_edge": bool(len(taus) > 1 and b in (0, len(taus) - 1)),
            "best_mean_score": float(s[:, b].mean()),
            "best_mean_score_x10^4.5": float(s[:, b].mean() * 10**4.5),
            "best_std_score": float(s[:, b].std(ddof=1)),
            "mean_nd_abs_error_at_best_tau": float(nd_err[:, b].mean()),
            "min_mean_nd_abs_error": float(nd_err.mean(axis=0).min()),
            "tau_of_min_nd_abs_error": taus[int(nd_err.mean(axis=0).argmin())],
            "mean_purity_at_best_tau": float(score_matrix(results, v, "purity")[:, b].mean()),
            "mean_gospa_m_at_best_tau": float(score_matrix(results, v, "gospa_m")[:, b].mean()),
            "mean_score_by_tau": s.mean(axis=0).tolist(),
            "std_score_by_tau": s.std(axis=0, ddof=1).tolist(),
            "mean_nd_abs_error_by_tau": nd_err.mean(axis=0).tolist(),
        }
        if len(poisson):
            p = poisson[poisson["algorithm"] == v].sort_values("seed")
            per_variant[v].update({
                "poisson_mean_score_x10^4.5": float(p["score"].mean() * 10**4.5),
                "poisson_mean_nd_abs_error": float(p["nd_abs_error"].mean()),
                "prob_poisson_better_than_best_tau": prob_better(p["score"].to_numpy() - s[:, b], "normal"),
            })
    config_dict = asdict(config)
    return {
        "config": config_dict,
        "taus": [float(t) for t in taus],
        "n_datasets": int(results["seed"].nunique()),
        "mean_targets_in_window": float(results.groupby("seed")["n_targets"].first().mean()),
        "mean_nd": float(results.groupby("seed")["nd"].first().mean()),
        "max_score_error_bound": float(results["score_error_bound"].max()),
        "variants": per_variant,
        "table_normal": comparison_table(scores, "normal", variants),
        "table_t": comparison_table(scores, "t", variants),
        "paper_table": PAPER_TABLE,
        "batch_vs_greedy": batch_vs_greedy(results, poisson, scores),
        "posterior_vs_greedy": batch_vs_greedy(results, poisson, scores, "posterior"),
    }


def _column_at(results: pd.DataFrame, algorithm: str, tau: float, column: str) -> np.ndarray:
    """One algorithm's ``column`` at one τ (NaN: the exact-S rows), per data set in seed order."""
    rows = results[results["algorithm"] == algorithm]
    rows = rows[rows["tau"].isna()] if np.isnan(tau) else rows[rows["tau"] == tau]
    return rows.sort_values("seed")[column].to_numpy(dtype=np.float64)


def batch_vs_greedy(results: pd.DataFrame, poisson: pd.DataFrame, scores: dict[str, np.ndarray],
                    method: str = "batch") -> dict:
    """Appendix B for ``method`` (batch or posterior) against greedy, per variant run by both, each
    algorithm at its own τ* (the best mean-Score τ) and, with Poisson rows, with the exact S: P(method
    better) on Score and on |N̂_D − N_D| (greedy's N̂_D its count; posterior's its posterior median;
    batch's at τ* its MAP count, with the exact S the posterior median ``nd_abs_error_bayes`` when
    present, keys ``exact_s_map_count`` with the MAP count); ln p(Λ|Z) of the MAP partition minus that
    of greedy's partition under batch's model per (data set, S) (``min_log_posterior_gain`` ≥ 0 when
    batch is never below greedy); for UU, the share of the UU → TT greedy gap in mean Score (τ*) that
    the method's UU closes."""
    out: dict[str, dict] = {}
    taus = sorted(results["tau"].unique())
    both = pd.concat([results, poisson])
    bayes = method == "batch" and "nd_abs_error_bayes" in both
    for v in VARIANTS:
        b, g = algorithm_name(v, method), v
        if b not in scores or g not in scores:
            continue
        tb, tg = (float(taus[best_tau_index(scores[x])]) for x in (b, g))
        gain = (score_matrix(results, b, "log_posterior") - score_matrix(results, b, "greedy_log_posterior")).ravel()
        row = {
            "best_tau": [tb, tg],
            "best_tau_at_grid_edge": [bool(t in (taus[0], taus[-1])) for t in (tb, tg)],
            "prob_better_score_best_tau": compare(scores[b], scores[g], "normal"),
            "prob_better_score_best_tau_t": compare(scores[b], scores[g], "t"),
            "mean_score_x10^4.5": [float(scores[x][:, best_tau_index(scores[x])].mean() * 10**4.5) for x in (b, g)],
            "min_log_posterior_gain": float(gain.min()),
            "mean_log_posterior_gain": float(gain.mean()),
        }
        settings = [("best_tau", tb, tg)]
        if len(poisson):
            pb = poisson[poisson["algorithm"] == b].sort_values("seed")
            pg = poisson[poisson["algorithm"] == g].sort_values("seed")
            row.update({
                "prob_better_score_exact_s": prob_better(pb["score"].to_numpy() - pg["score"].to_numpy(), "normal"),
                "mean_score_exact_s_x10^4.5": [float(x["score"].mean() * 10**4.5) for x in (pb, pg)],
                "min_log_posterior_gain_exact_s": float((pb["log_posterior"] - pb["greedy_log_posterior"]).min()),
            })
            settings.append(("exact_s", float("nan"), float("nan")))
        for name, t_b, t_g in settings:
            err_g = _column_at(both, g, t_g, "nd_abs_error")
            exact = name == "exact_s"
            for suffix, column in [("", "nd_abs_error_bayes" if bayes and exact else "nd_abs_error"),
                                   ("_map_count", "nd_abs_error" if bayes and exact else None)]:
                if column is None:
                    continue
                err_b = _column_at(both, b, t_b, column)
                row[f"prob_better_nd_error_{name}{suffix}"] = prob_better(err_b - err_g, "normal")
                row[f"prob_better_nd_error_{name}{suffix}_t"] = prob_better(err_b - err_g, "t")
                row[f"mean_nd_abs_error_{name}{suffix}"] = [float(err_b.mean()), float(err_g.mean())]
        out[v] = row
    if "UU" in out and "TT" in scores:
        uu = algorithm_name("UU", method)
        best = {a: float(scores[a][:, best_tau_index(scores[a])].mean()) for a in ("UU", uu, "TT")}
        gap = best["UU"] - best["TT"]
        out["UU"]["share_of_uu_tt_gap_closed"] = (best["UU"] - best[uu]) / gap if gap else None
        out["UU"]["prob_uu_batch_better_than_tt_greedy"] = compare(scores[uu], scores["TT"], "normal")
    return out


def write_results(results: pd.DataFrame, out_dir: str | os.PathLike) -> str:
    """``results.parquet`` in ``out_dir`` (created), or ``results.csv`` without pyarrow; returns its path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_paths(out / "results.parquet") as (tmp,):
            results.to_parquet(tmp, index=False)
        return str(out / "results.parquet")
    except ImportError:
        with atomic_paths(out / "results.csv") as (tmp,):
            results.to_csv(tmp, index=False)
        return str(out / "results.csv")


def write_outputs(results: pd.DataFrame, summary: dict, out_dir: str | os.PathLike, title: str = "") -> dict[str, str]:
    """Results table (Parquet, CSV if pyarrow is missing), summary JSON, Table 1 Markdown and figures."""
    out = Path(out_dir)
    paths = {"results": write_results(results, out)}
    with atomic_paths(out / "summary.json") as (tmp,):
        tmp.write_text(json.dumps(summary, indent=1))
    paths["summary"] = str(out / "summary.json")
    with atomic_paths(out / "table1.md") as (tmp,):
        tmp.write_text(
            "Normal form (paper's value in brackets):\n\n" + table_markdown(summary["table_normal"])
            + "\n\nt form:\n\n" + table_markdown(summary["table_t"]) + "\n"
        )
    paths["table"] = str(out / "table1.md")
    paths["figures"] = [str(p) for p in write_figures(results, out, title=title)]
    return paths


def run_and_write(
    prior_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    config: ExperimentConfig,
    workers: int | None = None,
    progress: bool = True,
    title: str = "",
) -> tuple[dict, dict]:
    """The ``terrain-track experiment`` command: run, summarise, write; returns (summary, paths)."""
    prior_path = Path(prior_path)
    prior = TerrainPrior.read(prior_path)  # fail fast, naming the file, before any worker starts
    if config.targets_file is not None:
        file_targets(config.targets_file, config.targets_layer, prior.grid)  # likewise a bad targets file or layer
    results = run_experiment(prior_path, config, workers=workers, progress=progress)
    summary = summarise(results, config)
    return summary, write_outputs(results, summary, out_dir, title=title or prior_path.stem)
