"""``terrain-prior``: build feature grids and priors from a region config, and draw them.

A thin argparse layer: one function per subcommand, each parses nothing itself and calls the library.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from pathlib import Path

from common.cli import count, quiet_parent, run_cli
from common.outputs import Output, command_outputs, input_files
from pipeline.build.region import (
    build_features,
    build_region_prior,
    region_provenance,
    write_features,
)
from pipeline.config.region import RegionConfig, load_config
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.prior.terrain import PriorError, TerrainPrior
from pipeline.prior.write import sat_paths


def config_inputs(config: RegionConfig) -> dict[str, list[Path]]:
    """The input files of a region config: the config itself and every layer's file(s), by label."""
    inputs = {f"region config {config.path.name}": [config.path]}
    for name, spec in config.layers.items():
        inputs[f"[layers.{name}] of {config.path.name}"] = input_files(spec.path)
    return inputs


def prior_inputs(path: Path) -> dict[str, list[Path]]:
    """The files of a prior set read as an input: the GeoTIFF and its summed-area tables."""
    return {f"prior {path}": [path, *sat_paths(path)]}


def file_inputs(**paths: Path | None) -> dict[str, list[Path]]:
    """``--name path`` inputs given on the command line (None: not given)."""
    return {f"--{k.replace('_', '-')} {p}": input_files(p) for k, p in paths.items() if p is not None}


def _wrote(paths: Iterable[Path]) -> str:
    return ", ".join(str(p) for p in paths)


def cmd_features(args: argparse.Namespace) -> None:
    config = load_config(args.region)
    with command_outputs([Output("--out", args.out, folder=True)], config_inputs(config)) as out:
        paths = write_features(build_features(config, progress=not args.quiet), out.path("--out"))
    print(f"wrote {len(paths)} feature GeoTIFFs to {args.out}: {', '.join(p.name for p in paths)}")


def cmd_build(args: argparse.Namespace) -> None:
    config = load_config(args.region)
    inputs = config_inputs(config) | file_inputs(model=args.model)
    with command_outputs([Output("--out", args.out)], inputs) as out:
        model = LikelihoodModel.read_toml(args.model) if args.model else None
        provenance = region_provenance(config, args.model)
        if args.tiled or args.scheduler:
            from common.dask import get_client  # dask loads only for tiled builds
            from pipeline.tiled.build import build_prior_tiled

            with get_client(args.scheduler) as client:
                s = build_prior_tiled(config, out.path("--out"), model, client, args.tile, provenance,
                                      progress=not args.quiet)
            done = f"{s['shape'][0]} x {s['shape'][1]} cells in {s['n_tiles']} tiles, {s['total_seconds']:.1f} s"
        else:
            prior = build_region_prior(config, model, not args.quiet, provenance)
            prior.write(out.path("--out"))
            done = f"{prior.grid.height} x {prior.grid.width} cells of {prior.grid.dx:g} m"
    print(f"wrote {args.out} ({done})")


def cmd_show(args: argparse.Namespace) -> None:
    from pipeline.show.plots import plot_features, plot_prior  # matplotlib loads only for `show`

    if not (args.png or args.html):
        raise ValueError("show: give --png, --html or both")
    prior = TerrainPrior.read(args.prior)
    inputs = prior_inputs(args.prior)
    region = args.region or prior.model.get("provenance", {}).get("config")
    config = load_config(region) if region is not None and (args.features_png or args.html) else None
    if config is not None:
        inputs |= config_inputs(config)
    if args.features_png:
        if region is None:
            raise PriorError(f"{args.prior}: records no region config; pass --region REGION.toml for --features-png")
    outputs = [Output("--png", args.png) if args.png else None,
               Output("--features-png", args.features_png) if args.features_png else None,
               Output("--html", args.html) if args.html else None]
    with command_outputs(outputs, inputs) as out:
        if args.png:
            plot_prior(prior, out.path("--png"))
        if args.features_png:
            plot_features(build_features(config, progress=not args.quiet), out.path("--features-png"))
        if args.html:
            from pipeline.show.html import write_prior_html  # folium loads only for --html

            write_prior_html(prior, out.path("--html"), config, args.basemap)
    print(f"wrote {_wrote(o.path for o in outputs if o is not None)}")


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="terrain-prior", description=__doc__.splitlines()[0],
                                     epilog="exit codes: 0 done, 1 error (an 'error:' line), 2 usage error")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    quiet = quiet_parent()
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("features", parents=[quiet], help="write one GeoTIFF per feature of a region config")
    p.add_argument("region", type=Path, help="region config (TOML)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.set_defaults(func=cmd_features)

    p = sub.add_parser("build", parents=[quiet], help="build a prior (prior.tif + summed-area tables beside it)")
    p.add_argument("region", type=Path, help="region config (TOML)")
    p.add_argument("--model", type=Path, help="likelihood tables (TOML) instead of the config's [likelihood.*]")
    p.add_argument("--out", type=Path, required=True, help="prior GeoTIFF to write")
    p.add_argument("--tiled", action="store_true", help="build tile by tile on Dask (a local in-process cluster without --scheduler)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler to run a tiled build on, e.g. tcp://10.0.0.5:8786 (implies --tiled)")
    p.add_argument("--tile", type=count(1), default=1024, help="tile edge in cells for tiled builds (default 1024)")
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("show", parents=[quiet], help="draw a prior (and its features) as PNG maps and/or an interactive HTML map")
    p.add_argument("prior", type=Path, help="prior GeoTIFF written by build")
    p.add_argument("--png", type=Path, help="prior map to write")
    p.add_argument("--html", type=Path, help="interactive map to write (one HTML file, opens offline; roads and water from the region config)")
    p.add_argument("--basemap", metavar="URL", help="--html: XYZ tile URL template drawn under the layers (default none: no network)")
    p.add_argument("--features-png", type=Path, help="feature maps to write (rebuilds the features)")
    p.add_argument("--region", type=Path, help="region config for --features-png and --html layers (default: the one the prior records)")
    p.set_defaults(func=cmd_show)
    add_learn_parser(sub, quiet)
    return parser


def cmd_learn(args: argparse.Namespace) -> None:
    from pipeline.config.learn import load_learn_config

    tiled = args.tiled or args.scheduler
    if tiled and args.hybrid_prior is not None:
        raise ValueError("--hybrid-prior needs the whole grid (the KDE term); it cannot be used with --tiled / --scheduler")
    if tiled and args.mixture_prior is not None:
        raise ValueError("--mixture-prior needs the whole grid (cross-fitted weights); it cannot be used with --tiled / --scheduler")
    config, lc = load_learn_config(args.region)
    if tiled and lc.mixture:
        raise ValueError(f"{args.region}: [learn.mixture] needs the whole grid (cross-fitted weights); it cannot be used with --tiled / --scheduler")
    if tiled and lc.select:
        raise ValueError(f"{args.region}: learn.select needs the whole grid (refits on block folds); it cannot be used with --tiled / --scheduler")
    inputs = config_inputs(config) | file_inputs(targets=args.targets)
    outputs = [Output("--out", args.out), Output("--hybrid-prior", args.hybrid_prior) if args.hybrid_prior else None,
               Output("--mixture-prior", args.mixture_prior) if args.mixture_prior else None]
    with command_outputs(outputs, inputs) as out:
        hybrid = out.path("--hybrid-prior") if args.hybrid_prior else None
        mixture = out.path("--mixture-prior") if args.mixture_prior else None
        if tiled and args.weights:
            raise ValueError("--weights: tiled learning (--tiled / --scheduler) is unweighted")
        if tiled:
            from pipeline.tiled.learn import learn_region_tiled  # dask loads only when tiled

            report = learn_region_tiled(args.region, args.targets, out.path("--out"), args.layer, args.x, args.y,
                                        args.targets_crs, scheduler=args.scheduler, tile=args.tile,
                                        progress=not args.quiet)
        else:
            # scikit-learn and the fit load only for `learn`
            from pipeline.learn.run import learn_region

            report = learn_region(args.region, args.targets, out.path("--out"), args.layer, args.x, args.y,
                                  args.targets_crs, cv=not args.no_cv, hybrid_prior=hybrid, progress=not args.quiet,
                                  weights=args.weights, mixture_prior=mixture)
        written = [out.final(p) for p in report.paths.values()]
    report.paths = dict(zip(report.paths, written, strict=True))
    print(report.table())
    print("wrote " + _wrote(written))


def add_learn_parser(sub, quiet: argparse.ArgumentParser) -> None:
    p = sub.add_parser("learn", parents=[quiet], help="fit the likelihood tables to past target points (Poisson-process ML)")
    p.add_argument("region", type=Path, help="region config (TOML); its [likelihood.*] tables are the template, [learn] the settings")
    p.add_argument("--targets", type=Path, required=True, help="past targets: GeoPackage/Shapefile/GeoJSON (centroids) or CSV with x,y")
    p.add_argument("--layer", help="layer of a multi-layer targets file")
    p.add_argument("--x", default="x", help="CSV column of x (default x)")
    p.add_argument("--y", default="y", help="CSV column of y (default y)")
    p.add_argument("--targets-crs", help="CRS of CSV coordinates (default: the grid's)")
    p.add_argument("--weights", metavar="COLUMN", help="targets column of per-point weights (> 0: a weight w counts as w targets there; "
                   "default [learn] weights, else all 1)")
    p.add_argument("--out", type=Path, required=True, help="fitted likelihood tables (TOML); diagnostics and plot beside it")
    p.add_argument("--no-cv", action="store_true", help="skip the spatial block cross-validation")
    p.add_argument("--hybrid-prior", type=Path, help="also write the hybrid (terrain + KDE) prior GeoTIFF here")
    p.add_argument("--mixture-prior", type=Path, help="also write the mixture prior of [learn.mixture] (GeoTIFF) here")
    p.add_argument("--tiled", action="store_true",
                   help="compute the fit's statistics tile by tile on Dask (grids larger than memory); implies --no-cv, no hybrid")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler for --tiled, e.g. tcp://10.0.0.5:8786 (implies --tiled)")
    p.add_argument("--tile", type=count(1), default=1024, help="tile edge in cells for --tiled (default 1024)")
    p.set_defaults(func=cmd_learn)


def main(argv: list[str] | None = None) -> int:
    """Run ``terrain-prior`` on ``argv``; the exit code (0 done, 1 error, 2 usage: :func:`common.cli.run_cli`)."""
    return run_cli("terrain-prior", make_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
