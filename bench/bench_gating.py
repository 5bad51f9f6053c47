"""Gating benchmarks (issues 5 and 18): static and moving 100k x 100k scenes against baselines
measured in the same run, the cost model's M_D against the empirical best (per round),
brute-force speed-up, adversarial scenes against numpy brute force + lexsort, 1 M x 1 M static
against cKDTree, and the scaling curve (plot in bench/figures/gating_scaling.png).

Scenes: uniform density of one object per km^2, position sigma 10-100 m (random orientation),
gate probability 0.99 (gamma = chi2.ppf(0.99, 2) = 9.21).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from sklearn.neighbors import BallTree

from bench.timing import best_time
from tracker.gating.calibrate import calibrate, moving_scene, random_covs
from tracker.gating.costmodel import CostConstants
from tracker.gating.exact import lambda_max_bound
from tracker.gating.gate import gate, gate_threshold
from tracker.study.projections import predicted_choice

FIGURES = Path(__file__).resolve().parent / "figures"
GAMMA = gate_threshold(0.99, 2)
# Calls per setting and round in the moving sweeps (best of them, one pass over all settings per call): auto and every candidate alike.
MOVING_INNER = 5


def static_scene(n: int, seed: int = 0):
    """n tracks and n reports, uniform at 1 per km^2 (metres), sigma 10-100 m."""
    rng = np.random.default_rng(seed)
    side = 1000.0 * np.sqrt(n)
    return (rng.uniform(0, side, (n, 2)), random_covs(rng, n, 10, 100),
            rng.uniform(0, side, (n, 2)), random_covs(rng, n, 10, 100))


def _exact_d2(tm, tc, rm, rc, i, j):
    v = tc[i] + rc[j]
    dx = rm[j] - tm[i]
    det = v[:, 0, 0] * v[:, 1, 1] - v[:, 0, 1] ** 2
    return (v[:, 1, 1] * dx[:, 0] ** 2 - 2 * v[:, 0, 1] * dx[:, 0] * dx[:, 1]
            + v[:, 0, 0] * dx[:, 1] ** 2) / det


def _finish(tm, tc, rm, rc, i, j, gamma):
    keep = _exact_d2(tm, tc, rm, rc, i, j) <= gamma
    i, j = i[keep], j[keep]
    o = np.lexsort((j, i))
    return i[o], j[o]


def _lists_to_pairs(lists):
    counts = np.fromiter(map(len, lists), np.int64, len(lists))
    j = np.repeat(np.arange(len(lists)), counts)
    i = np.concatenate(lists).astype(np.int64) if counts.sum() else np.zeros(0, np.int64)
    return i, j


def reference_kdtree(tm, tc, rm, rc, gamma=GAMMA, workers=1):
    """The issue's reference: cKDTree on tracks, query_ball_point per report with radius
    sqrt(gamma (lambda_max(R) + max lambda_max(P))), then the exact test (vectorised)."""
    lam_p = np.linalg.eigvalsh(tc)[:, -1].max()
    lam_r = np.linalg.eigvalsh(rc)[:, -1]
    tree = cKDTree(tm)
    lists = tree.query_ball_point(rm, np.sqrt(gamma * (lam_r + lam_p)) * (1 + 1e-9),
                                  workers=workers)
    return _finish(tm, tc, rm, rc, *_lists_to_pairs(lists), gamma)


def reference_balltree(tm, tc, rm, rc, gamma=GAMMA):
    """scikit-learn BallTree on tracks, query_radius per report (the design card's tree)."""
    lam_p = lambda_max_bound(tc).max()
    lam_r = lambda_max_bound(rc)
    lists = BallTree(tm).query_radius(rm, np.sqrt(gamma * (lam_r + lam_p)) * (1 + 1e-9))
    return _finish(tm, tc, rm, rc, *_lists_to_pairs(list(lists)), gamma)


def reference_ball_tree_pairs(tm, tc, rm, rc, gamma=GAMMA):
    """cKDTree on both sets, query_ball_tree with the global maximum radius."""
    r = np.sqrt(gamma * (lambda_max_bound(tc).max() + lambda_max_bound(rc).max()))
    lists = cKDTree(rm).query_ball_tree(cKDTree(tm), r * (1 + 1e-9))
    return _finish(tm, tc, rm, rc, *_lists_to_pairs(lists), gamma)


def numpy_brute(tm, tc, rm, rc, gamma=GAMMA, chunk=32):
    """Every pair, vectorised numpy on covariance components, in cache-sized chunks of tracks."""
    r00, r01, r11 = rc[:, 0, 0], rc[:, 0, 1], rc[:, 1, 1]
    out_i, out_j = [], []
    for s in range(0, len(tm), chunk):
        t = slice(s, s + chunk)
        v00 = tc[t, 0, 0, None] + r00
        v01 = tc[t, 0, 1, None] + r01
        v11 = tc[t, 1, 1, None] + r11
        dx = rm[:, 0] - tm[t, 0, None]
        dy = rm[:, 1] - tm[t, 1, None]
        d2 = (v11 * dx * dx - 2 * v01 * dx * dy + v00 * dy * dy) / (v00 * v11 - v01 * v01)
        i, j = np.nonzero(d2 <= gamma)
        out_i.append(i + s)
        out_j.append(j)
    return np.concatenate(out_i), np.concatenate(out_j)


def interleaved(fns: dict, rounds: int, per_round: list | None = None,
                inner: int = 1) -> tuple[dict, dict]:
    """Fastest wall time per callable, timing them round-robin so that load changes on a
    shared machine hit every candidate alike; also the last result of each. Within a round
    each callable's time is the best of ``inner`` calls (one timing of a 30 ms call carries the
    machine's scatter), taken in ``inner`` passes over all the callables rather than back to
    back: this VM's host runs everything up to ~1.3x slower for seconds at a time, and ``inner``
    back-to-back calls of one setting could all fall in such a spell while another's all miss it.
    Each pass takes the callables in a new random order, so none always follows the same one (a
    call after one of the same setting finds its caches warm). Each round's times are appended to
    ``per_round`` (a dict per round) when given."""
    best = dict.fromkeys(fns, np.inf)
    out = {}
    keys = list(fns)
    rng = np.random.default_rng(0)
    for _ in range(rounds):
        this = dict.fromkeys(fns, np.inf)
        for _ in range(inner):
            for i in rng.permutation(len(keys)):
                key = keys[i]
                t0 = time.perf_counter()
                out[key] = fns[key]()
                this[key] = min(this[key], time.perf_counter() - t0)
        for key in fns:
            best[key] = min(best[key], this[key])
        if per_round is not None:
            per_round.append(this)
    return best, out


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def bench_static(n: int, repeats: int) -> dict:
    tm, tc, rm, rc = static_scene(n)
    gate(tm[:10], tc[:10], rm[:10], rc[:10], threshold=GAMMA)  # compile / load cache
    t, res = interleaved({
        "gate": lambda: gate(tm, tc, rm, rc, threshold=GAMMA),
        "ref": lambda: reference_kdtree(tm, tc, rm, rc),
        "ref2": lambda: reference_kdtree(tm, tc, rm, rc, workers=-1),
        "ball": lambda: reference_balltree(tm, tc, rm, rc),
        "qbt": lambda: reference_ball_tree_pairs(tm, tc, rm, rc),
    }, repeats)
    best_ref = min(t["ref"], t["ref2"])
    fastest = min(t["ref"], t["ref2"], t["ball"], t["qbt"])
    return {
        "n": n, "pairs": int(res["gate"][0].size),
        "gate_s": t["gate"], "ref_kdtree_s": t["ref"], "ref_kdtree_2workers_s": t["ref2"],
        "balltree_s": t["ball"], "kdtree_query_ball_tree_s": t["qbt"],
        "speedup_vs_ref": best_ref / t["gate"],
        "speedup_vs_fastest_baseline": fastest / t["gate"],
        "identical_to_refs": bool(all(_same(res["gate"], res[k])
                                      for k in ("ref", "ref2", "ball", "qbt"))),
        "goal_s": 0.25, "goal_met": bool(t["gate"] <= 0.25 and best_ref / t["gate"] >= 2.0),
    }


def bench_brute(n: int, subset: int, repeats: int) -> dict:
    tm, tc, rm, rc = static_scene(n)
    t_sub, _ = best_time(lambda: numpy_brute(tm[:subset], tc[:subset], rm, rc), repeats)
    t_gate, _ = best_time(lambda: gate(tm, tc, rm, rc, threshold=GAMMA), repeats)
    scaled = t_sub * n / subset
    return {"n": n, "subset": subset, "brute_scaled_s": scaled, "gate_s": t_gate,
            "speedup": scaled / t_gate, "goal": 300.0}


def bench_moving(n: int, rounds: int, ms: list[int], constants: CostConstants,
                 per_km2: float = 1.0) -> dict:
    """Sweep M_D and both orientations (round-robin); compare with the cost model's pick under
    ``constants``."""
    tm, tc, rm, rc, rt = moving_scene(n, per_km2=per_km2)
    kw = dict(threshold=GAMMA, report_times=rt, process_noise=1.0)
    gate(tm[:10], tc[:10], rm[:10], rc[:10], threshold=GAMMA, report_times=rt[:10])
    choice = predicted_choice(tm, tc, rm, rc, rt, threshold=GAMMA, process_noise=1.0,
                              constants=constants)
    chosen = f"{'reports' if choice.on_reports else 'tracks'}:{choice.m}"
    configs = [(o, m) for o in ("reports", "tracks") for m in ms]
    if chosen not in {f"{o}:{m}" for o, m in configs}:
        configs.append(("reports" if choice.on_reports else "tracks", choice.m))
    fns = {f"{o}:{m}": (lambda o=o, m=m: gate(tm, tc, rm, rc, **kw, n_projections=m,
                                              orientation=o)) for o, m in configs}
    fns["auto"] = lambda: gate(tm, tc, rm, rc, **kw, constants=constants)
    rounds_s: list[dict] = []
    sweep, res = interleaved(fns, rounds, rounds_s, inner=MOVING_INNER)
    t_auto = sweep.pop("auto")
    best_key = min(sweep, key=sweep.get)
    t_one = min(sweep["reports:1"], sweep["tracks:1"])
    # Per round, each timing the best of MOVING_INNER back-to-back calls: auto (cost model
    # included) against the best setting (the run's fastest) timed in the same round — the goal
    # figure —, and against the least of all settings' timings in that round. The second divides by
    # the minimum of 14-19 scattered timings, so it exceeds 1 even for an exact pick; the best
    # setting's own time over that minimum is its noise floor (what a perfect pick would score).
    auto_over_best = [r["auto"] / r[best_key] for r in rounds_s]
    round_min = [min(v for k, v in r.items() if k != "auto") for r in rounds_s]
    return {
        "n": n, "per_km2": per_km2, "pairs": int(res["auto"][0].size), "sweep_s": sweep,
        "auto_over_best_per_round": auto_over_best,
        "auto_over_best_worst": max(auto_over_best),
        "auto_over_round_min_per_round": [r["auto"] / lo for r, lo in zip(rounds_s, round_min, strict=True)],
        "best_over_round_min_per_round": [r[best_key] / lo for r, lo in zip(rounds_s, round_min, strict=True)],
        "identical": bool(all(_same(res["auto"], v) for v in res.values())),
        "chosen": chosen, "predicted_chosen_s": float(min(choice.cost_tracks.min(),
                                                          choice.cost_reports.min())),
        "chosen_s": sweep[chosen], "auto_total_s": t_auto, "best": best_key,
        "best_s": sweep[best_key], "chosen_over_best": sweep[chosen] / sweep[best_key],
        "speedup_vs_md1": t_one / sweep[chosen], "goal_s": 1.5,
        "goal_met": bool(t_auto <= 1.5 and max(auto_over_best) <= 1.2),
    }


def brute_sorted(tm, tc, rm, rc, gamma=GAMMA):
    """The issue's bar: numpy brute force over every pair, then a lexsort of its output."""
    i, j = numpy_brute(tm, tc, rm, rc, gamma)
    o = np.lexsort((j, i))
    return i[o], j[o]


def adversarial_scenes(quick: bool) -> dict:
    """Static scenes that defeat a grid: (tracks, track covs, reports, report covs)."""
    rng = np.random.default_rng(0)
    out = {}
    for m in ([30_000] if quick else [100_000, 300_000]):  # the repro
        n = 1001
        tm = rng.uniform(0, 1e4, (n, 2))
        tc = np.tile(np.diag([400.0, 400.0]), (n, 1, 1))
        tm[0], tc[0] = 5000.0, np.diag([1e10, 1e10])  # this track gates every report
        out[f"one huge track, 1001 x {m}"] = (tm, tc, rng.uniform(0, 1e4, (m, 2)),
                                               np.tile(np.diag([25.0, 25.0]), (m, 1, 1)))
    n, m = (1000, 5000) if quick else (3000, 10_000)
    out[f"{n} tracks at one point, {m} spread reports"] = (
        np.full((n, 2), 5000.0), np.tile(np.eye(2) * 700.0**2, (n, 1, 1)),
        rng.uniform(0, 1e4, (m, 2)), np.tile(np.eye(2) * 25.0, (m, 1, 1)))
    n = 700 if quick else 2000
    out[f"everything at one point, {n} x {n}"] = (
        np.zeros((n, 2)), np.tile(np.eye(2), (n, 1, 1)), np.zeros((n, 2)),
        np.tile(np.eye(2), (n, 1, 1)))
    n = 3000 if quick else 10_000
    side = 1000.0 * np.sqrt(n)  # 1 per km^2, sigma log-uniform 1 m .. 10 km on both sides
    sig = lambda k: np.exp(rng.uniform(0.0, np.log(1e4), k))  # noqa: E731
    out[f"radii over 4 decades, {n} x {n}"] = (
        rng.uniform(0, side, (n, 2)), np.eye(2) * (sig(n) ** 2)[:, None, None],
        rng.uniform(0, side, (n, 2)), np.eye(2) * (sig(n) ** 2)[:, None, None])
    return out


def bench_adversarial(quick: bool, repeats: int) -> list[dict]:
    """gate against numpy brute force + lexsort on each adversarial scene (round-robin)."""
    rows = []
    gate(np.zeros((1, 2)), np.eye(2)[None], np.zeros((1, 2)), np.eye(2)[None], threshold=GAMMA)
    for name, sc in adversarial_scenes(quick).items():
        t, res = interleaved({"gate": lambda sc=sc: gate(*sc, threshold=GAMMA),
                              "brute": lambda sc=sc: brute_sorted(*sc)}, repeats)
        rows.append({"scene": name, "pairs": int(res["gate"][0].size), "gate_s": t["gate"],
                     "brute_lexsort_s": t["brute"], "gate_over_brute": t["gate"] / t["brute"],
                     "identical": _same(res["gate"], res["brute"]),
                     "goal_met": bool(t["gate"] <= t["brute"])})
    return rows


def bench_static_1m(n: int) -> dict:
    """Static n x n (goal: 1 M x 1 M in <= 0.4 s) with the cKDTree reference in the same run."""
    tm, tc, rm, rc = static_scene(n)
    gate(tm[:10], tc[:10], rm[:10], rc[:10], threshold=GAMMA)
    t, res = interleaved({"gate": lambda: gate(tm, tc, rm, rc, threshold=GAMMA),
                          "ref2": lambda: reference_kdtree(tm, tc, rm, rc, workers=-1)}, 2)
    return {"n": n, "pairs": int(res["gate"][0].size), "gate_s": t["gate"],
            "ref_kdtree_2workers_s": t["ref2"], "speedup_vs_ref": t["ref2"] / t["gate"],
            "identical": _same(res["gate"], res["ref2"]), "goal_s": 0.4,
            "goal_met": bool(t["gate"] <= 0.4)}


def bench_scaling(sizes: list[int], ref_max: int) -> dict:
    rows = []
    for n in sizes:
        scene = static_scene(n)
        reps = 3 if n <= 100_000 else 1
        t_gate, _ = best_time(lambda s=scene: gate(*s, threshold=GAMMA), reps)
        t_ref = best_time(lambda s=scene: reference_kdtree(*s), reps)[0] if n <= ref_max \
            else None
        rows.append({"n": n, "gate_s": t_gate, "ref_kdtree_s": t_ref})
    ns = np.array([r["n"] for r in rows], float)
    ts = np.array([r["gate_s"] for r in rows])
    big = ns >= 1e4
    slope = float(np.polyfit(np.log(ns[big]), np.log(ts[big]), 1)[0]) if big.sum() >= 2 else None
    _plot_scaling(rows)
    return {"rows": rows, "loglog_slope_n_ge_1e4": slope}


def _ratios(m: dict, key: str = "auto_over_best_per_round") -> str:
    return ", ".join(f"{x:.2f}" for x in m[key])


def _plot_scaling(rows) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ns = np.array([r["n"] for r in rows], float)
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.loglog(ns, [r["gate_s"] for r in rows], "o-", label="gate (grid + exact, numba)")
    ref = [(r["n"], r["ref_kdtree_s"]) for r in rows if r["ref_kdtree_s"] is not None]
    if ref:
        ax.loglog(*zip(*ref, strict=True), "s--", label="reference (cKDTree + exact)")
    t_last = rows[-1]["gate_s"]
    guide = t_last * ns * np.log(ns) / (ns[-1] * np.log(ns[-1]))
    ax.loglog(ns, guide, ":", color="grey", label="N log N")
    ax.set_xlabel("objects per side (tracks = reports)")
    ax.set_ylabel("wall time (s)")
    ax.set_title("Static 2-D gating, 1 object/km$^2$")
    ax.legend()
    fig.tight_layout()
    FIGURES.mkdir(parents=True, exist_ok=True)
    tmp = FIGURES / "gating_scaling.tmp.png"
    fig.savefig(tmp, dpi=120)
    os.replace(tmp, FIGURES / "gating_scaling.png")
    plt.close(fig)


def run(quick: bool = False) -> dict:
    """All gating benchmarks; quick=True uses small scenes (< 60 s)."""
    n = 10_000 if quick else 100_000
    reps = 2 if quick else 3
    sweep = [1, 2, 4, 8] if quick else [1, 2, 3, 4, 6, 8, 12]
    constants = calibrate(n=n)  # measured in this run: the cost model's picks below use them
    out = {
        "static": bench_static(n, reps),
        "moving": bench_moving(n, reps, sweep, constants),
        "moving_dense": bench_moving(5000 if quick else 30_000, reps, sweep + [16, 24], constants,
                                     per_km2=100.0),
        "brute": bench_brute(n, 100 if quick else 300, 1),
        "adversarial": bench_adversarial(quick, min(reps, 2)),
        "static_1m": bench_static_1m(100_000 if quick else 1_000_000),
        "scaling": bench_scaling([1000, 3000, 10_000, 30_000] if quick else
                                 [1000, 3000, 10_000, 30_000, 100_000, 300_000, 1_000_000],
                                 30_000 if quick else 300_000),
        "cost_constants": constants.__dict__,
        "load_average_1_5_15min": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
    }
    s, m, b, md = out["static"], out["moving"], out["brute"], out["moving_dense"]
    big, adv = out["static_1m"], out["adversarial"]
    worst_adv = max(adv, key=lambda r: r["gate_over_brute"])
    out["table"] = [
        {"what": f"static {big['n']} x {big['n']}", "value": f"{big['gate_s']:.3f} s",
         "goal": "<= 0.4 s", "same-run baseline": f"cKDTree, 2 workers: {big['ref_kdtree_2workers_s']:.3f} s "
                                                  f"({big['speedup_vs_ref']:.1f}x slower)",
         "meets_goal": big["goal_met"]},
        {"what": f"static {n} x {n}", "value": f"{s['gate_s']:.3f} s", "goal": "<= 0.25 s, >= 2x cKDTree",
         "same-run baseline": f"cKDTree {min(s['ref_kdtree_s'], s['ref_kdtree_2workers_s']):.3f} s "
                              f"({s['speedup_vs_ref']:.1f}x)",
         "meets_goal": s["goal_met"]},
        *[{"what": f"moving {r['n']} x {r['n']} at {r['per_km2']:g}/km^2: auto / best, worst round",
           "value": f"{r['auto_over_best_worst']:.2f} (rounds {_ratios(r)}; auto {r['auto_total_s']:.3f} s; "
                    f"the pick {r['chosen']} best of rounds / the best setting's: {r['chosen_over_best']:.2f})",
           "goal": "<= 1.2 in every round", "same-run baseline":
               f"the best of {len(r['sweep_s'])} settings ({r['best']}, {r['best_s']:.3f} s at best) timed in the same round, "
               f"each timing the best of {MOVING_INNER} calls; auto / the least timing of each round: "
               f"{_ratios(r, 'auto_over_round_min_per_round')} (the best setting's own: {_ratios(r, 'best_over_round_min_per_round')})",
           "meets_goal": r["goal_met"]} for r in (m, md)],
        {"what": f"adversarial scenes ({len(adv)}): gate / (brute force + lexsort), worst",
         "value": f"{worst_adv['gate_over_brute']:.3f} ({worst_adv['scene']})", "goal": "<= 1 on every scene",
         "same-run baseline": "numpy brute force + lexsort per scene",
         "meets_goal": all(r["goal_met"] and r["identical"] for r in adv)},
        f"static {n}x{n}: gate {s['gate_s']:.3f} s, cKDTree ref {s['ref_kdtree_s']:.3f} s "
        f"(2 workers {s['ref_kdtree_2workers_s']:.3f} s), BallTree {s['balltree_s']:.3f} s, "
        f"speed-up {s['speedup_vs_ref']:.1f}x (vs fastest baseline "
        f"{s['speedup_vs_fastest_baseline']:.1f}x)",
        f"moving {n}x{n} 10 s scan: auto {m['auto_total_s']:.3f} s, chosen {m['chosen']} "
        f"{m['chosen_s']:.3f} s, best {m['best']} {m['best_s']:.3f} s "
        f"(ratio {m['chosen_over_best']:.2f}), {m['speedup_vs_md1']:.1f}x over M_D=1",
        f"moving {md['n']}x{md['n']} at 100/km^2: chosen {md['chosen']} {md['chosen_s']:.3f} s, "
        f"best {md['best']} {md['best_s']:.3f} s (ratio {md['chosen_over_best']:.2f}), "
        f"{md['speedup_vs_md1']:.1f}x over M_D=1",
        f"moving auto/best per round: sparse {_ratios(m)}, dense {_ratios(md)}",
        f"brute force (numpy, scaled from {b['subset']}) {b['brute_scaled_s']:.1f} s: "
        f"{b['speedup']:.0f}x",
        f"static {out['static_1m']['n']}x{out['static_1m']['n']}: gate "
        f"{out['static_1m']['gate_s']:.3f} s, cKDTree ref (2 workers) "
        f"{out['static_1m']['ref_kdtree_2workers_s']:.3f} s "
        f"({out['static_1m']['speedup_vs_ref']:.1f}x)",
        *[f"adversarial: {r['scene']} ({r['pairs']} pairs): gate {r['gate_s']:.3f} s, brute + "
          f"lexsort {r['brute_lexsort_s']:.3f} s, ratio {r['gate_over_brute']:.3f}"
          for r in out["adversarial"]],
        f"scaling log-log slope (n>=1e4): {out['scaling']['loglog_slope_n_ge_1e4']:.2f}",
        f"machine load average during the run: {out['load_average_1_5_15min'][1]:.1f} "
        f"(5 min) on {out['cpu_count']} cores",
    ]
    return out
