"""``terrain-track``: run the association-estimation tracker on a file of reports.

A thin argparse layer: one function per subcommand, each parses nothing itself and calls the library.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from common.cli import count, number, quiet_parent, run_cli
from common.outputs import Output, command_outputs, input_files
from tracker.association import DEFAULT_GAMMA, VARIANTS
from tracker.integrate import METHODS
from tracker.models.motion import ConstantVelocity, Static
from tracker.models.sfunc import ExpS, PoissonS
from tracker.run import ASSOCIATION_METHODS, DEFAULT_SWEEPS

if TYPE_CHECKING:
    from common.maps import VectorSource


def prior_inputs(path: Path) -> dict[str, list[Path]]:
    """The files of a prior set read as an input: the GeoTIFF and its summed-area tables."""
    from pipeline.prior import sat_paths

    return {f"--prior {path}": [path, *sat_paths(path)]}


def file_inputs(**paths: Path | None) -> dict[str, list[Path]]:
    """``--name path`` inputs given on the command line (None: not given)."""
    return {f"--{k.replace('_', '-')} {p}": input_files(p) for k, p in paths.items() if p is not None}


def cmd_run(args: argparse.Namespace) -> None:
    from functools import partial

    from tracker.integrate import integrate_checked
    from tracker.run import track_files

    s_model = PoissonS(args.poisson_mu) if args.poisson_mu is not None else ExpS(args.tau)
    motion = ConstantVelocity(args.q, args.velocity_std) if args.motion == "cv" else Static()
    outputs = [Output("--out", args.out), Output("--assignments", args.assignments) if args.assignments else None]
    with contextlib.ExitStack() as stack:
        out = stack.enter_context(command_outputs(outputs, prior_inputs(args.prior) | file_inputs(reports=args.reports)))
        if args.scheduler:
            from common.dask import get_client  # dask loads only for cluster runs
            from tracker.integrate.lazy import tile_client

            stack.enter_context(tile_client(stack.enter_context(get_client(args.scheduler))))
        result = track_files(
            args.prior, args.reports, out.path("--out"), args.variant, s_model, motion, layer=args.layer,
            ellipse_prob=args.ellipse_prob, assignments_csv=out.path("--assignments") if args.assignments else None,
            method=args.method, sweeps=args.sweeps, samples=args.samples, seed=args.seed, progress=not args.quiet,
            gamma=args.gamma, off_prior=args.off_prior, integrator=partial(integrate_checked, method=args.integrator),
        )
    skipped = int((result.assignments < 0).sum())
    print(f"{len(result.assignments)} reports -> {result.n_detected} targets ({args.variant}, {s_model}, {args.method}); "
          f"{skipped} skipped; wrote {args.out}" + (f" and {args.assignments}" if args.assignments else ""))
    if result.log_posterior is not None:
        print(f"ln p(partition | reports) + const: greedy {result.greedy_log_posterior:.3f}, batch {result.log_posterior:.3f}")


def add_integrator_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--integrator", choices=METHODS, default="scalespace",
                   help="how Gaussians are integrated against the prior: the prior's Gaussian pyramid (default, fast; "
                        "~17 float32 per cell of memory) or the paper's terraces on its summed-area tables")


def add_run_parser(sub, quiet: argparse.ArgumentParser) -> None:
    p = sub.add_parser("run", parents=[quiet], help="associate reports (in file order) and write the estimated targets")
    p.add_argument("--prior", type=Path, required=True, help="prior GeoTIFF (terrain-prior build)")
    p.add_argument("--reports", type=Path, required=True, help="CSV or GeoPackage: x, y, time, cov_xx, cov_xy, cov_yy")
    p.add_argument("--layer", help="layer of a multi-layer reports file")
    p.add_argument("--variant", choices=VARIANTS, default="TT", help="UU, UT or TT (paper 1, section 6); default TT")
    s = p.add_mutually_exclusive_group()
    s.add_argument("--tau", type=number(), default=-1.7, help="S(n,k) = exp(-n tau); default -1.7 (the paper's best TT)")
    s.add_argument("--poisson-mu", type=number(0), help="exact eq. 16 with a Poisson(mu) number of targets instead of tau")
    p.add_argument("--method", choices=ASSOCIATION_METHODS, default="greedy",
                   help="greedy (paper 1, in file order; default) or batch (search over partitions from greedy's, docs/batch.md)")
    p.add_argument("--sweeps", type=count(0), help=f"batch: annealed Gibbs sweeps (map mode) or burn-in sweeps (with --samples); default {DEFAULT_SWEEPS}")
    p.add_argument("--samples", type=count(1), help="batch: sample the posterior for this many sweeps (membership from the samples) instead of the MAP search")
    p.add_argument("--seed", type=count(0), help="batch: seed of the chain's random scan order and moves; default 0")
    p.add_argument("--motion", choices=("static", "cv"), default="static", help="static targets or constant velocity")
    p.add_argument("--q", type=number(0, strict=False), default=0.1, help="cv: white-noise acceleration density, m^2/s^3")
    p.add_argument("--velocity-std", type=number(0), default=10.0, help="cv: initial velocity std per axis, m/s")
    p.add_argument("--gamma", type=number(0), default=DEFAULT_GAMMA, help="gate on d^2 (speed only; decisions do not depend on it)")
    p.add_argument("--off-prior", choices=("raise", "skip"), default="raise", help="reports where the prior has no mass")
    add_integrator_argument(p)
    p.add_argument("--ellipse-prob", type=number(0, 1), default=0.95, help="probability contour drawn as each target's ellipse")
    p.add_argument("--assignments", type=Path, help="also write report -> hypothesis index as CSV (batch: and its membership probability)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler whose workers build the prior's pyramid tiles, for "
                   "priors above 25 M cells (read window by window; the file must be on a path the workers share)")
    p.add_argument("--out", type=Path, required=True, help="GeoPackage to write (layers targets, ellipses)")
    p.set_defaults(func=cmd_run)


def add_targets_file_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--targets-file", type=Path, help="real target locations: a vector file (points, or polygon centroids) "
                   "or a CSV with x, y columns; each data set picks --targets of those in its window (seeded)")
    p.add_argument("--layer", help="layer of a multi-layer --targets-file")


def cmd_experiment(args: argparse.Namespace) -> None:
    from tracker.study.experiment import ExperimentConfig, parse_taus, run_and_write
    from tracker.study.simulate import AirborneSensor

    config = ExperimentConfig(
        n_datasets=args.datasets, n_reports=args.reports, taus=parse_taus(args.tau),
        variants=tuple(args.variants.split(",")), n_targets=args.targets, base_seed=args.seed,
        sensor=AirborneSensor(azimuth_std_rad=args.azimuth_std_mrad / 1000.0, range_std_m=args.range_std_m),
        poisson_mu=args.poisson_mu, integrator=args.integrator, methods=tuple(args.methods.split(",")),
        targets_file=str(args.targets_file) if args.targets_file else None, targets_layer=args.layer,
    )
    title = args.title or ""
    inputs = prior_inputs(args.prior) | file_inputs(targets_file=args.targets_file)
    with command_outputs([Output("--out", args.out, folder=True)], inputs) as out:
        if args.scheduler:
            from common.dask import get_client  # dask loads only for cluster runs
            from tracker.study.sweep import run_and_write_dask

            with get_client(args.scheduler) as client:
                summary, paths = run_and_write_dask(args.prior, out.path("--out"), config, client,
                                                    progress=not args.quiet, title=title)
        else:
            summary, paths = run_and_write(args.prior, out.path("--out"), config, workers=args.workers,
                                           progress=not args.quiet, title=title)
        paths = {k: [out.final(p) for p in v] if isinstance(v, list) else out.final(v) for k, v in paths.items()}
    for v, d in summary["variants"].items():
        print(f"{v}: best tau {d['best_tau']:+.2f}, mean score x10^4.5 {d['best_mean_score_x10^4.5']:.2f}, "
              f"|N_D^ - N_D| {d['mean_nd_abs_error_at_best_tau']:.2f}"
              + (f"; exact S: {d['poisson_mean_score_x10^4.5']:.2f}" if "poisson_mean_score_x10^4.5" in d else ""))
    for method in ("batch", "posterior"):
        for v, d in summary[f"{method}_vs_greedy"].items():
            print(f"{v} {method} vs greedy: P(better score) {d['prob_better_score_best_tau']:.3f}, "
                  f"P(better |N_D^ - N_D|) {d['prob_better_nd_error_best_tau']:.3f}, min ln p gain {d['min_log_posterior_gain']:.3g}")
    print(f"wrote {paths['results']}, {paths['summary']}, {paths['table']} and {len(paths['figures'])} figures")


def add_experiment_parser(sub, quiet: argparse.ArgumentParser) -> None:
    p = sub.add_parser("experiment", parents=[quiet], help="paper 1's simulation: UU, UT, TT over a tau grid on seeded data sets")
    p.add_argument("--prior", type=Path, required=True, help="prior GeoTIFF (terrain-prior build)")
    p.add_argument("--datasets", type=count(2), default=28, help="number of data sets (seeds seed..seed+n-1); default 28")
    p.add_argument("--reports", type=count(1), default=100, help="reports per data set; default 100")
    p.add_argument("--tau", default="-3:3:0.25", help="start:stop:step (stop included) or a comma list; default -3:3:0.25")
    p.add_argument("--variants", default="UU,UT,TT", help="comma list of UU, UT, TT")
    p.add_argument("--methods", default="greedy", help="comma list of greedy, batch, posterior (batch: MAP search from greedy's "
                   "partition; posterior: batch's Bayes estimates from a posterior sample started at the MAP, "
                   "the posterior-mean mixture and the posterior median of N_D)")
    p.add_argument("--targets", type=count(1), default=200, help="targets drawn over the 14 km region before the window "
                   "(with --targets-file: picked among the file's locations in the window); default 200")
    add_targets_file_arguments(p)
    p.add_argument("--seed", type=count(0), default=0, help="seed of the first data set")
    p.add_argument("--poisson-mu", type=number(0), help="also run every variant with the exact eq. 16 S under Poisson(mu)")
    p.add_argument("--azimuth-std-mrad", type=number(0), default=2.0, help="sensor azimuth standard deviation, mrad")
    p.add_argument("--range-std-m", type=number(0), default=12.0, help="sensor slant-range standard deviation, m")
    add_integrator_argument(p)
    p.add_argument("--workers", type=count(1), help="local worker processes (default: all cores; 1 runs inline)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler to spread the data sets over, e.g. tcp://10.0.0.5:8786 (instead of --workers)")
    p.add_argument("--title", help="figure title prefix (default: the prior's file name)")
    p.add_argument("--out", type=Path, required=True, help="output folder (results, summary.json, table1.md, PNGs)")
    p.set_defaults(func=cmd_experiment)


def cmd_heldout(args: argparse.Namespace) -> None:
    from tracker.study.experiment import parse_taus
    from tracker.study.heldout import HeldoutConfig, run_and_write_heldout
    from tracker.study.simulate import AirborneSensor

    try:
        alphas = tuple(float(a) for a in args.alphas.split(","))
    except ValueError:
        raise ValueError(f"--alphas {args.alphas!r}: expected a comma list of numbers >= 0") from None
    config = HeldoutConfig(
        region=str(args.region), targets_file=str(args.targets_file), targets_layer=args.layer, block_m=args.block_m,
        n_folds=args.folds, n_datasets=args.datasets, n_targets=args.targets, n_reports=args.reports,
        taus=parse_taus(args.tau), alphas=alphas, hybrid=not args.no_hybrid, handset=not args.no_handset,
        other_region=not args.no_other, exact_s=not args.no_exact_s, batch=args.batch, base_seed=args.seed,
        sensor=AirborneSensor(azimuth_std_rad=args.azimuth_std_mrad / 1000.0, range_std_m=args.range_std_m),
        integrator=args.integrator,
    )
    inputs = file_inputs(region=args.region, targets_file=args.targets_file)
    with command_outputs([Output("--out", args.out, folder=True)], inputs) as out:
        summary, paths = run_and_write_heldout(config, out.path("--out"), workers=args.workers, progress=not args.quiet)
        paths = {k: out.final(v) for k, v in paths.items()}
    for key, entry in summary["table"]["gospa_m"].items():
        pur = summary["table"]["purity"][key]
        print(f"{key}: P(better) GOSPA {entry['t']:.3f}, purity {pur['t']:.3f} (t form, best tau)")
    print(f"{summary['n_datasets']} data sets in {len(summary['blocks'])} held-out blocks; wrote {paths['table']}, {paths['summary']}")


def add_heldout_parser(sub, quiet: argparse.ArgumentParser) -> None:
    p = sub.add_parser("heldout", parents=[quiet], help="learn the prior from targets in training blocks, track real "
                       "targets in held-out blocks, compare priors (docs/experiment.md)")
    p.add_argument("--region", type=Path, required=True, help="region TOML (features, hand-set tables, [learn])")
    p.add_argument("--targets-file", type=Path, required=True, help="past target locations: vector file (points or polygon centroids) or CSV x, y")
    p.add_argument("--layer", help="layer of a multi-layer --targets-file")
    p.add_argument("--targets", type=count(1), default=50, help="targets per data set, picked in a held-out block; default 50")
    p.add_argument("--datasets", type=count(2), default=28, help="data sets (held-out blocks in turn); default 28")
    p.add_argument("--reports", type=count(1), default=100, help="reports per data set; default 100")
    p.add_argument("--tau", default="-9:3:0.25", help="start:stop:step (stop included) or a comma list; default -9:3:0.25 (wider than the paper's: dense sets want tau < -3)")
    p.add_argument("--block-m", type=number(0), default=2000.0, help="side of the spatial blocks = data-set windows, m; default 2000")
    p.add_argument("--folds", type=count(2), default=5, help="block folds; each held-out block's prior is learned from the other folds; default 5")
    p.add_argument("--alphas", default="0,0.5,1,1.5,2", help="exponents of the misspecified priors r^alpha; default 0,0.5,1,1.5,2")
    p.add_argument("--no-hybrid", action="store_true", help="leave out the learned hybrid prior")
    p.add_argument("--no-handset", action="store_true", help="leave out the config's hand-set tables")
    p.add_argument("--no-other", action="store_true", help="leave out the model learned on another (the furthest) fold")
    p.add_argument("--no-exact-s", action="store_true", help="leave out the exact eq. 16 S under Poisson(--targets)")
    p.add_argument("--batch", action="store_true", help="also run batch TT (MAP partition from greedy's) with the learned prior")
    p.add_argument("--seed", type=count(0), default=0, help="seed of the first data set")
    p.add_argument("--azimuth-std-mrad", type=number(0), default=2.0, help="sensor azimuth standard deviation, mrad")
    p.add_argument("--range-std-m", type=number(0), default=12.0, help="sensor slant-range standard deviation, m")
    add_integrator_argument(p)
    p.add_argument("--workers", type=count(1), help="local worker processes (default: all cores; 1 runs inline)")
    p.add_argument("--out", type=Path, required=True, help="output folder (results, summary.json, table.md, alpha.png, priors/)")
    p.set_defaults(func=cmd_heldout)


def cmd_simulate(args: argparse.Namespace) -> None:
    from pipeline.prior import TerrainPrior
    from tracker.io.reports import write_reports, write_targets
    from tracker.study.simulate import file_targets, simulate, simulate_points

    outputs = [Output("--out", args.out), Output("--truth-out", args.truth_out) if args.truth_out else None]
    with command_outputs(outputs, prior_inputs(args.prior) | file_inputs(targets_file=args.targets_file)) as out:
        prior = TerrainPrior.read(args.prior)
        if args.targets_file:
            points = file_targets(args.targets_file, args.layer, prior.grid)
            scenario = simulate_points(prior, points, args.seed, args.targets, args.reports, source=str(args.targets_file))
        else:
            scenario = simulate(prior, args.seed, args.targets, args.reports)
        write_reports(out.path("--out"), scenario.reports)
        if args.truth_out:
            write_targets(out.path("--truth-out"), scenario.targets)
    msg = f"{len(scenario.reports)} reports of {scenario.n_detected} of {len(scenario.targets)} targets; wrote {args.out}"
    print(msg + (f" and {args.truth_out}" if args.truth_out else ""))


def add_simulate_parser(sub, quiet: argparse.ArgumentParser) -> None:
    p = sub.add_parser("simulate", parents=[quiet], help="simulate one data set of the paper's experiment (targets from the prior, airborne sensor)")
    p.add_argument("--prior", type=Path, required=True, help="prior GeoTIFF (terrain-prior build)")
    p.add_argument("--seed", type=count(0), default=0, help="random seed")
    p.add_argument("--targets", type=count(1), default=200, help="targets drawn over the central 14 km (kept: the central half); "
                   "with --targets-file: picked among the file's locations in the central half")
    add_targets_file_arguments(p)
    p.add_argument("--reports", type=count(1), default=100, help="reports, targets picked with replacement")
    p.add_argument("--truth-out", type=Path, help="also write the kept true targets as CSV (truth, x, y)")
    p.add_argument("--out", type=Path, required=True, help="reports CSV to write")
    p.set_defaults(func=cmd_simulate)


def cmd_show(args: argparse.Namespace) -> None:
    from pipeline.prior import TerrainPrior
    from tracker.io.reports import read_reports, read_targets
    from tracker.io.tracks import read_tracks
    from tracker.study.plots import tracks_figure

    if not (args.png or args.html):
        raise ValueError("show: give --png, --html or both")
    inputs = prior_inputs(args.prior) | file_inputs(reports=args.reports, tracks=args.tracks, truth=args.truth)
    inputs |= {f"--vector {v.path}": input_files(v.path) for v in args.vector}
    outputs = [Output("--png", args.png) if args.png else None, Output("--html", args.html) if args.html else None]
    with command_outputs(outputs, inputs) as out:
        prior = TerrainPrior.read(args.prior)
        reports, _ = read_reports(args.reports)
        means, covs, counts = read_tracks(args.tracks)
        targets = read_targets(args.truth) if args.truth else None
        if args.png:
            tracks_figure(prior, reports.means, reports.covs, means, covs, out.path("--png"), targets=targets)
        if args.html:
            from tracker.study.maps import tracks_map  # folium loads only for --html

            tracks_map(prior, reports.means, reports.covs, means, covs, counts, targets=targets,
                       basemap=args.basemap, vectors=args.vector).save(out.path("--html"), title="reports and estimated targets")
    print("wrote " + ", ".join(str(o.path) for o in outputs if o is not None))


def vector_source(text: str) -> VectorSource:
    """The argparse type of ``--vector``: :meth:`common.maps.VectorSource.parse` (a bad value is a usage error)."""
    from common.maps import VectorSource  # folium loads only when a map is drawn

    try:
        return VectorSource.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_show_parser(sub, quiet: argparse.ArgumentParser) -> None:
    p = sub.add_parser("show", parents=[quiet], help="draw reports and estimated targets over the prior as a PNG map and/or an interactive HTML map")
    p.add_argument("--prior", type=Path, required=True, help="prior GeoTIFF")
    p.add_argument("--reports", type=Path, required=True, help="reports CSV or GeoPackage")
    p.add_argument("--tracks", type=Path, required=True, help="tracks GeoPackage (terrain-track run)")
    p.add_argument("--truth", type=Path, help="true targets CSV (terrain-track simulate --truth-out)")
    p.add_argument("--png", type=Path, help="PNG to write")
    p.add_argument("--html", type=Path, help="interactive map to write (one HTML file, opens offline)")
    p.add_argument("--basemap", metavar="URL", help="--html: XYZ tile URL template drawn under the layers (default none: no network)")
    p.add_argument("--vector", metavar="PATH[:LAYER][=NAME]", type=vector_source, action="append", default=[],
                   help="--html: also draw this layer of a vector file (e.g. region.gpkg:lakes=water; LAYER may be "
                        "left out for a file of one layer, NAME defaults to LAYER), each its own overlay; repeatable")
    p.set_defaults(func=cmd_show)


def cmd_calibrate(args: argparse.Namespace) -> None:
    from tracker.gating.calibrate import calibrate

    with command_outputs([Output("--out", args.out)], {}) as out:
        constants = calibrate(out=out.path("--out"))
    print(f"gating cost constants (s per unit): {constants}; wrote {args.out} "
          f"(use: gate(..., constants=CostConstants.read({str(args.out)!r})))")


def add_calibrate_parser(sub, quiet: argparse.ArgumentParser) -> None:
    p = sub.add_parser("calibrate", parents=[quiet], help="time gate() on this machine (about 10 s) and write the cost model's constants")
    p.add_argument("--out", type=Path, default=Path("gating_costs.json"),
                   help="JSON file to write (default gating_costs.json); read it with CostConstants.read")
    p.set_defaults(func=cmd_calibrate)


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="terrain-track", description=__doc__.splitlines()[0],
                                     epilog="exit codes: 0 done, 1 error (an 'error:' line), 2 usage error")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = parser.add_subparsers(dest="command", required=True)
    quiet = quiet_parent()
    for add in (add_run_parser, add_experiment_parser, add_heldout_parser, add_simulate_parser, add_show_parser, add_calibrate_parser):
        add(sub, quiet)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``terrain-track`` on ``argv``; the exit code (0 done, 1 error, 2 usage: :func:`common.cli.run_cli`)."""
    return run_cli("terrain-track", make_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
