"""``terrain-prior``: build feature grids and priors from a region config, and draw them.

A thin argparse layer: one function per subcommand, each parses nothing itself and calls the library.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from pipeline.build.region import (
    build_features,
    build_region_prior,
    region_provenance,
    write_features,
)
from pipeline.config.region import load_config
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.prior.terrain import PriorError, TerrainPrior
from pipeline.show.plots import plot_features, plot_prior


def cmd_features(args: argparse.Namespace) -> None:
    config = load_config(args.region)
    paths = write_features(build_features(config, progress=not args.quiet), args.out)
    print(f"wrote {len(paths)} feature GeoTIFFs to {args.out}: {', '.join(p.name for p in paths)}")


def cmd_build(args: argparse.Namespace) -> None:
    config = load_config(args.region)
    model = LikelihoodModel.read_toml(args.model) if args.model else None
    provenance = region_provenance(config, args.model)
    if args.tiled or args.scheduler:
        from common.dask import get_client  # dask loads only for tiled builds
        from pipeline.tiled.build import build_prior_tiled

        with get_client(args.scheduler) as client:
            s = build_prior_tiled(config, args.out, model, client, args.tile, provenance, progress=not args.quiet)
        print(f"wrote {args.out} ({s['shape'][0]} x {s['shape'][1]} cells in {s['n_tiles']} tiles, {s['total_seconds']:.1f} s)")
        return
    prior = build_region_prior(config, model, not args.quiet, provenance)
    prior.write(args.out)
    print(f"wrote {args.out} ({prior.grid.height} x {prior.grid.width} cells of {prior.grid.dx:g} m)")


def cmd_show(args: argparse.Namespace) -> None:
    if not (args.png or args.html):
        raise ValueError("show: give --png, --html or both")
    prior = TerrainPrior.read(args.prior)
    if args.png:
        plot_prior(prior, args.png)
        print(f"wrote {args.png}")
    region = args.region or prior.model.get("provenance", {}).get("config")
    if args.features_png:
        if region is None:
            raise PriorError(f"{args.prior}: records no region config; pass --region REGION.toml for --features-png")
        plot_features(build_features(load_config(region), progress=not args.quiet), args.features_png)
        print(f"wrote {args.features_png}")
    if args.html:
        from pipeline.show.html import write_prior_html  # folium loads only for --html

        write_prior_html(prior, args.html, load_config(region) if region else None, args.basemap)
        print(f"wrote {args.html}")


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="terrain-prior", description=__doc__.splitlines()[0])
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("features", help="write one GeoTIFF per feature of a region config")
    p.add_argument("region", type=Path, help="region config (TOML)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.set_defaults(func=cmd_features)

    p = sub.add_parser("build", help="build a prior (prior.tif + summed-area tables beside it)")
    p.add_argument("region", type=Path, help="region config (TOML)")
    p.add_argument("--model", type=Path, help="likelihood tables (TOML) instead of the config's [likelihood.*]")
    p.add_argument("--out", type=Path, required=True, help="prior GeoTIFF to write")
    p.add_argument("--tiled", action="store_true", help="build tile by tile on Dask (a local in-process cluster without --scheduler)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler to run a tiled build on, e.g. tcp://10.0.0.5:8786 (implies --tiled)")
    p.add_argument("--tile", type=int, default=1024, help="tile edge in cells for tiled builds (default 1024)")
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("show", help="draw a prior (and its features) as PNG maps and/or an interactive HTML map")
    p.add_argument("prior", type=Path, help="prior GeoTIFF written by build")
    p.add_argument("--png", type=Path, help="prior map to write")
    p.add_argument("--html", type=Path, help="interactive map to write (one HTML file, opens offline; roads and water from the region config)")
    p.add_argument("--basemap", metavar="URL", help="--html: XYZ tile URL template drawn under the layers (default none: no network)")
    p.add_argument("--features-png", type=Path, help="feature maps to write (rebuilds the features)")
    p.add_argument("--region", type=Path, help="region config for --features-png and --html layers (default: the one the prior records)")
    p.set_defaults(func=cmd_show)
    add_learn_parser(sub)
    return parser


def cmd_learn(args: argparse.Namespace) -> None:
    if args.tiled or args.scheduler:
        if args.hybrid_prior is not None:
            raise ValueError("--hybrid-prior needs the whole grid (the KDE term); it cannot be used with --tiled / --scheduler")
        from pipeline.tiled.learn import learn_region_tiled  # dask loads only for tiled learning

        report = learn_region_tiled(args.region, args.targets, args.out, args.layer, args.x, args.y, args.targets_crs,
                                    scheduler=args.scheduler, tile=args.tile, progress=not args.quiet)
    else:
        # scikit-learn and the fit load only for `learn`
        from pipeline.learn.run import learn_region

        report = learn_region(args.region, args.targets, args.out, args.layer, args.x, args.y, args.targets_crs,
                              cv=not args.no_cv, hybrid_prior=args.hybrid_prior, progress=not args.quiet)
    print(report.table())
    print("wrote " + ", ".join(str(p) for p in report.paths.values()))


def add_learn_parser(sub) -> None:
    p = sub.add_parser("learn", help="fit the likelihood tables to past target points (Poisson-process ML)")
    p.add_argument("region", type=Path, help="region config (TOML); its [likelihood.*] tables are the template, [learn] the settings")
    p.add_argument("--targets", type=Path, required=True, help="past targets: GeoPackage/Shapefile/GeoJSON (centroids) or CSV with x,y")
    p.add_argument("--layer", help="layer of a multi-layer targets file")
    p.add_argument("--x", default="x", help="CSV column of x (default x)")
    p.add_argument("--y", default="y", help="CSV column of y (default y)")
    p.add_argument("--targets-crs", help="CRS of CSV coordinates (default: the grid's)")
    p.add_argument("--out", type=Path, required=True, help="fitted likelihood tables (TOML); diagnostics and plot beside it")
    p.add_argument("--no-cv", action="store_true", help="skip the spatial block cross-validation")
    p.add_argument("--hybrid-prior", type=Path, help="also write the hybrid (terrain + KDE) prior GeoTIFF here")
    p.add_argument("--tiled", action="store_true",
                   help="compute the fit's statistics tile by tile on Dask (grids larger than memory); implies --no-cv, no hybrid")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler for --tiled, e.g. tcp://10.0.0.5:8786 (implies --tiled)")
    p.add_argument("--tile", type=int, default=1024, help="tile edge in cells for --tiled (default 1024)")
    p.set_defaults(func=cmd_learn)


def main(argv: list[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="terrain-prior: %(message)s")
    try:
        args.func(args)
    except ValueError as exc:  # every input problem is a ValueError naming the file, layer or value
        print(f"terrain-prior: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
