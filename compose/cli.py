"""The ``zenswarm`` command. Each subcommand lives with the code it runs; this file only wires them.

Run ``zenswarm --help`` and ``zenswarm SUBCOMMAND --help``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from zenswarm.bridge.args import (
    add_flight_args,
    add_full_time_arg,
    add_override_args,
    add_plugin_args,
    link_faults,
    positive_float,
    scenario_of,
)
from zenswarm.bridge.cli import BRIDGE_COMMANDS
from zenswarm.errors import run_command

EPILOG = """\
Quick start:
  zenswarm sim compose/scenarios/paper_example1.toml --out runs/sim1
  zenswarm up  compose/scenarios/paper_example1.toml --out runs/ex1

Exit codes: 0 success, 1 mission failed, 2 bad input (the message names the field, flag or file;
checked before any work starts, output paths included), 3 a swarm process failed, 4 a plug-in
failed (``plugin_error``), 130 interrupted.
"""


def _add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim",
        help="run a scenario in one process (the in-process reference simulator)",
        description=(
            "Fly SCENARIO in one process, vectorised over UAVs, with the same discrete-time "
            "semantics as the distributed lockstep swarm. Writes OUT/results.json and "
            "OUT/timeseries.npz. Exit status 0 when the mission succeeded (the leader reached the "
            "goal, every UAV ended at its slot, no contact with obstacles, the ground or each other, "
            "every state finite), 1 otherwise (each failure named with its cause and time), 4 when a plug-in "
            "failed (it raised, or gave a non-finite or wrongly shaped output: plugin_error, named with the plug-in, UAV, "
            "tick and cause; what was flown before is judged and written), 130 on Ctrl-C (what was flown is judged and written)."
        ),
    )
    p.add_argument("scenario", type=Path, help="scenario TOML file, e.g. compose/scenarios/paper_example1.toml")
    p.add_argument("--out", type=Path, default=Path("runs/sim"), help="output directory (default: runs/sim)")
    p.add_argument("--no-eso", action="store_true", help="disable the ESO disturbance compensation (d_hat = 0 in eq. 28)")
    p.add_argument(
        "--fixed-gain",
        type=positive_float,
        metavar="K",
        help="use the fixed-gain APF with K_rep = K instead of the adaptive gain (12), for comparison",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    add_full_time_arg(p)
    add_flight_args(p)
    p.set_defaults(func=_run_sim)


def _run_sim(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from zenswarm.compose.sim import apply_overrides, run_sim_cli
    from zenswarm.process.paths import check_output_dir
    from zenswarm.scenario.plugins import check_selection

    sc, _ = scenario_of(args)  # --set, --duration, --controller, --planner: checked, plug-ins included
    sc = apply_overrides(sc, no_eso=args.no_eso, fixed_gain=args.fixed_gain)
    if args.seed is not None:
        sc = replace(sc, seed=args.seed)
    check_selection(sc)
    faults = link_faults(args).plan(sc)
    check_output_dir(args.out, "--out")  # before the flight: a run must not be lost at the end
    return run_sim_cli(sc, args.out, quiet=args.quiet, faults=faults, full_time=args.full_time)


def _add_scenario(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenario", help="check or generate scenario files", description="Scenario file tools.")
    ssub = p.add_subparsers(dest="scenario_cmd", metavar="{check,generate}", required=True)
    c = ssub.add_parser(
        "check",
        help="validate a scenario file and print a summary",
        description=(
            "Load and validate SCENARIO exactly as a flight does, the plug-ins included (their names resolve, their "
            "[agents.params] / [leader.params] decode); print its summary or the error naming the bad field (exit 2)."
        ),
    )
    c.add_argument("scenario", type=Path)
    add_plugin_args(c)
    add_override_args(c)
    c.set_defaults(func=_run_check)
    from zenswarm.compose.scenario_generate import add_parser as add_generate

    add_generate(ssub)


def _run_check(args: argparse.Namespace) -> int:
    from zenswarm.scenario.plugins import planner_name

    s, _ = scenario_of(args)
    print(
        f"{args.scenario}: OK  name={s.name}  N={s.n}  r_f={s.r_f:.3f} m  obstacles={len(s.obstacles)}  "
        f"control {s.timing.control_rate_hz:g} Hz  physics {s.timing.physics_rate_hz:g} Hz  "
        f"time limit {s.timing.time_limit_s:g} s  controller {s.agents.controller}  planner {planner_name(s)}  "
        f"plant model {s.plant.model}"
    )
    return 0


def _add_plugins(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plugins",
        help="list the available agent controllers, leader planners and plant models",
        description=(
            "List the controllers, planners and plant models a scenario can name ([agents] controller, [leader] planner, "
            "[plant] model, --controller, --planner, --plant-model): the built-ins and the installed entry points (groups "
            "zenswarm.controllers, zenswarm.planners, zenswarm.plants), with a one-line description each. Any other "
            "plug-in is named module:attribute."
        ),
    )
    psub = p.add_subparsers(dest="plugins_cmd", metavar="{list,check}")
    psub.add_parser("list", help="list them (the default)").set_defaults(func=_run_plugins)
    from zenswarm.compose.plugcheck import add_check_parser

    add_check_parser(psub)
    p.set_defaults(func=_run_plugins)


def _run_plugins(args: argparse.Namespace) -> int:
    from zenswarm.scenario.plugins import DEFAULTS, KINDS, available

    for kind in KINDS:
        print(f"{kind}s (default {DEFAULTS[kind]}):")
        for info in available(kind):
            print(f"  {info.name:<12} {info.description}  [{info.origin}: {info.target}]")
    return 0


def _add_sweep(sub: argparse._SubParsersAction) -> None:
    # Listed here for `zenswarm --help`; the console command (zenswarm.__main__) hands `sweep` to
    # zenswarm.sweep before this parser (it flies through zenswarm.api, above this layer).
    p = sub.add_parser(
        "sweep",
        help="experiment campaigns: grids, samples and seeds in parallel (local pool or Dask); sweep report, sweep margin",
        add_help=False,
    )
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_run_sweep_here)


def _run_sweep_here(args: argparse.Namespace) -> int:
    print("zenswarm: error: sweep runs through the zenswarm command (zenswarm.__main__, python -m zenswarm sweep ...)", file=sys.stderr)
    return 2


#: The subcommands the front door's own functions register, by name (``zenswarm --help`` lists them first).
_OWN = {"sim": _add_sim, "scenario": _add_scenario, "plugins": _add_plugins, "sweep": _add_sweep}

#: The modules that register the other subcommands (their ``add_parsers(sub)``), with the names
#: each registers, in the order ``zenswarm --help`` lists them. ``zenswarm COMMAND ...`` builds
#: the parser of its own module only (:func:`build_parser`), so it imports what it runs and not the
#: whole CLI; ``tests/test_cli_parsers.py`` holds this table against the whole parser.
_MODULES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("zenswarm.compose.up", ("up",)),
    ("zenswarm.compose.roles", ("plant", "mavlink-vehicle", "crazyflie-vehicle", "leader", "agent")),
    ("zenswarm.bridge.cli", BRIDGE_COMMANDS),
    ("zenswarm.compose.keys", ("keys",)),
)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``zenswarm`` parser: every subcommand, or with ``command`` (a subcommand's name) only
    the subcommands registered with it, which parse and print ``--help`` as in the whole parser."""
    parser = argparse.ArgumentParser(
        prog="zenswarm",
        description=(
            "Hierarchical distributed formation flight and 3D obstacle avoidance for quadrotor "
            "swarms: AAPF virtual leader (eqs 8-15), distributed reference generator (16-17), "
            "ESO-based tracking (27-28), one OS process per UAV over Zenoh."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, add in _OWN.items():
        if command in (None, name):
            add(sub)
    for modname, names in _MODULES:
        if command is not None and command not in names:
            continue
        try:
            mod = __import__(modname, fromlist=["add_parsers"])
        except ImportError as e:
            if e.name and modname.startswith(e.name):
                continue  # subsystem not installed in this build
            raise
        if modname == "zenswarm.bridge.cli":
            mod.add_parsers(sub, only=command)
        else:
            mod.add_parsers(sub)
    return parser


def _known(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names (its first word), if it is one: only its parser is built."""
    name = argv[0] if argv else None
    return name if name in _OWN or any(name in names for _, names in _MODULES) else None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("agent", "leader", "plant"):  # the swarm's own processes: only their parser
        from zenswarm.compose.roles import run_role

        return run_role(argv)
    from zenswarm.compose.commands import edge_of

    if argv[:2] == ["up", "--settings"]:  # api.fly's supervisor: its typed settings on stdin (not in `up --help`)
        from zenswarm.compose.up import run_settings_argv

        def func() -> int:
            return run_settings_argv(argv[1:])
    elif edge_of(argv) is not None:  # an edge process of `zenswarm up`: its typed settings on stdin (not in its --help)
        from zenswarm.compose.commands import run_edge

        def func() -> int:
            return run_edge(argv)
    else:
        args = build_parser(_known(argv)).parse_args(argv)

        def func() -> int:
            return int(args.func(args) or 0)
    return run_command(func)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
