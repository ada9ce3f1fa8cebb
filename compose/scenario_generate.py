"""``zenswarm scenario generate``: the command line of :func:`zenswarm.scenario.generate.generate_scenario`
(write a random but valid scenario file)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from zenswarm.bridge.args import positive_float, seed_arg
from zenswarm.errors import ZenswarmError
from zenswarm.process.paths import check_output_file
from zenswarm.scenario.generate import PINNINGS, SHAPES, TOPOLOGIES, generate_scenario, to_toml

__all__ = ["add_parser", "run_generate"]


def _positive_int(s: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def _nonneg_int(s: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    """Register ``generate`` under the ``scenario`` command's sub-parsers; returns the parser.

    The parser sets ``func`` to a callable(args) -> exit status (0 written, 2 bad input).
    """
    p = subparsers.add_parser(
        "generate",
        help="write a random but valid scenario file (N UAVs, formation, graph, obstacles)",
        description=(
            "Generate a scenario TOML with N UAVs in a formation shape, a connected communication "
            "graph (written by name: [graph] topology, and k for knn), pinning that satisfies Lemma 1 "
            "(M = L + B positive definite) and seeded, "
            "non-overlapping capped-cylinder obstacles between the leader's start and goal. "
            "Gains are the paper's. The file is validated before it is written."
        ),
    )
    p.add_argument("--n", type=_positive_int, default=3, help="number of follower UAVs N (default: 3)")
    p.add_argument("--shape", choices=SHAPES, default="circle", help="formation shape of the offsets h_i (default: circle)")
    p.add_argument(
        "--topology",
        choices=TOPOLOGIES,
        default="ring",
        help="communication graph among UAVs; knn = k nearest formation neighbours, symmetrised and made connected (default: ring)",
    )
    p.add_argument("--k", type=_positive_int, default=2, help="neighbours per UAV for --topology knn, clamped to N-1 (default: 2)")
    p.add_argument(
        "--pinning",
        choices=PINNINGS,
        default="first",
        help="which UAVs hear the virtual leader (b_i = 1): first = UAV 1, all, random = each with p=0.3, at least one (default: first)",
    )
    p.add_argument(
        "--obstacles",
        type=_nonneg_int,
        default=0,
        metavar="COUNT",
        help="number of capped-cylinder obstacles (radius 0.10-0.25 m, height 0.3-1.0 m) placed between start and goal (default: 0)",
    )
    p.add_argument(
        "--seed",
        type=seed_arg,
        default=0,
        help="integer 0 to 2**63-1 seeding the jitter, random pinning and obstacles; also written as scenario.seed (default: 0)",
    )
    p.add_argument(
        "--spacing",
        type=positive_float,
        default=0.3,
        metavar="METRES",
        help="distance between neighbouring UAVs in the formation, m (default: 0.3)",
    )
    p.add_argument(
        "--time-limit",
        type=positive_float,
        default=None,
        metavar="SECONDS",
        help="mission time limit, s (default: from the start-goal distance, at least 70 s)",
    )
    p.add_argument("--name", default=None, help="scenario name (default: gen_<shape>_<topology>_n<N>_s<seed>)")
    p.add_argument("--out", type=Path, required=True, metavar="FILE", help="TOML file to write (required)")
    p.add_argument("--force", action="store_true", help="overwrite FILE if it exists (default: refuse)")
    p.set_defaults(func=run_generate)
    return p


def run_generate(args: argparse.Namespace) -> int:
    """The ``scenario generate`` command: generate, validate, write ``args.out``; exit status."""
    out: Path = check_output_file(args.out, "--out")
    if out.exists() and not args.force:
        print(f"zenswarm: error: {out} exists; pass --force to overwrite it", file=sys.stderr)
        return 2
    try:
        d = generate_scenario(
            args.n,
            shape=args.shape,
            topology=args.topology,
            k=args.k,
            pinning=args.pinning,
            n_obstacles=args.obstacles,
            seed=args.seed,
            spacing=args.spacing,
            name=args.name,
            time_limit_s=args.time_limit,
        )
    except (ValueError, ZenswarmError) as e:
        print(f"zenswarm: error: {e}", file=sys.stderr)
        return 2
    argv = " ".join(
        [f"--n {args.n} --shape {args.shape} --topology {args.topology}"]
        + ([f"--k {args.k}"] if args.topology == "knn" else [])
        + [f"--pinning {args.pinning} --obstacles {args.obstacles} --seed {args.seed} --spacing {args.spacing:g}"]
    )
    header = (
        f"# Generated by: zenswarm scenario generate {argv}\n"
        "# Gains are the paper's (example 1); see zenswarm/scenario/generate.py for the geometry.\n\n"
    )
    text = header + to_toml(d)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "w" if args.force else "x", encoding="utf-8") as f:
            f.write(text)
    except FileExistsError:
        print(f"zenswarm: error: {out} exists; pass --force to overwrite it", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"zenswarm: error: cannot write {out}: {e}", file=sys.stderr)
        return 2
    r_f = float(np.max(np.linalg.norm(np.asarray(d["formation"]["offsets"]), axis=1)))
    dist = float(np.linalg.norm(np.subtract(d["leader"]["goal"], d["leader"]["start"])))
    print(
        f"wrote {out}: {d['scenario']['name']}  N={args.n} {args.shape}  graph={args.topology}  "
        f"pinned={int(sum(d['graph']['pinning']))}  obstacles={len(d['obstacles'])}  r_f={r_f:.3f} m  "
        f"start->goal {dist:.2f} m  time limit {d['timing']['time_limit_s']:g} s  seed {args.seed}"
    )
    return 0
