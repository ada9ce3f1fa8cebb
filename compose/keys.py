"""``zenswarm keys``: the command line of :func:`zenswarm.process.security.generate_credentials`."""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import sys
from pathlib import Path

from zenswarm.errors import ScenarioError
from zenswarm.process import security
from zenswarm.process.paths import check_output_dir

__all__ = ["add_parsers"]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add ``zenswarm keys``."""
    p = sub.add_parser(
        "keys",
        help="generate credentials for an authenticated swarm (users, passwords, CA, certificates)",
        description=(
            "Generate credentials for every process of SCENARIO (plant, leader, agent:1..N, "
            "recorder, bridge, supervisor): a user name and random password each (for "
            "`zenswarm up --secure`), and a CA with one certificate and key each (mutual TLS, "
            "`--secure --tls`). Keys and passwords are written 0600. Copy OUT/<process>/ to the "
            "host that runs that process; OUT/router/ and OUT/supervisor/ to the router's host; "
            "keep OUT/ca/ca-key.pem off the swarm. See docs/security.md."
        ),
    )
    p.add_argument("scenario", type=Path, help="scenario TOML file (its graph sets the access rules' shape)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--swarm", default="default", help="swarm name (key prefix swarm/<name>); default: default")
    p.add_argument(
        "--router-host",
        action="append",
        default=[],
        metavar="HOST",
        help="a DNS name or IP address other hosts use to reach the router (repeatable); "
        "localhost, 127.0.0.1 and ::1 are always included",
    )
    p.add_argument(
        "--days", type=int, default=security.DEFAULT_DAYS, help=f"certificate validity in days (default {security.DEFAULT_DAYS})"
    )
    p.add_argument("--force", action="store_true", help="replace existing credentials in OUT")
    p.set_defaults(func=_run_keys)


def _run_keys(args: argparse.Namespace) -> int:
    if args.days < 1:  # the flag's name, not the library's argument's
        raise ScenarioError("--days", f"expected a certificate validity of at least 1 day, got {args.days}")
    try:
        _dt.datetime.now(_dt.UTC) + _dt.timedelta(days=args.days + 1)
    except OverflowError:
        raise ScenarioError("--days", f"{args.days} days from now is past the year 9999 (a certificate's last date)") from None
    check_output_dir(args.out, "--out")
    m = security.generate_credentials(
        args.scenario, args.out, args.swarm, router_hosts=args.router_host, days=args.days, force=args.force
    )
    rel = lambda p: os.path.relpath(p, Path.cwd())  # noqa: E731
    print(f"credentials for swarm '{m.swarm}' (scenario {m.scenario}, {m.n} UAVs) in {rel(m.root)}:")
    print(f"  {rel(m.ca_cert)}  CA certificate (valid until {m.not_after})")
    print(f"  {rel(m.ca_key)}  CA private key (0600): keep it off the swarm's hosts")
    print(f"  {rel(m.usrpwd_file)}  user:password dictionary (0600): router host only")
    for p in m.processes:
        extra = f"  router names: {', '.join(m.router_hosts)}" if p.process == security.ROUTER_PROCESS else ""
        print(f"  {rel(p.dir)}/  {p.process:<11} user {p.user}; credentials.json, key.pem (0600), cert.pem, ca.pem{extra}")
    print(f"  {rel(m.root / security.MANIFEST_FILE)}  manifest (no secrets)")
    sys.stdout.flush()
    return 0
