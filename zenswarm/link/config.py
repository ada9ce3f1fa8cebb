"""A run's fault plan from the scenario's ``[faults]`` table and the command line's shortcuts.

:func:`plan_from_scenario` reads the ``[faults]`` table of a scenario, :func:`plan_from_cli` the
``--link-delay``, ``--link-jitter``, ``--link-loss`` and ``--partition`` shortcuts. Example::

    [faults]
    delay = "50ms"            # every directed link, unless a [[faults.links]] entry matches
    jitter = "10ms"
    loss = 0.2                # independent drop probability, [0, 1]
    burst = { p_good_to_bad = 0.01, p_bad_to_good = 0.25 }   # optional Gilbert-Elliott
    partitions = ["agent:2@10s-13s", "agent:1->agent:3@20s-21.5s"]

    [[faults.links]]          # later entries win; omitted fields inherit [faults]
    src = "agent:*"           # glob over process names; default "*"
    dst = "agent:3"
    kind = "ref"              # ref | leader | state | cmd | "*"; default "*"
    delay = "100ms"
    loss = 0.0
    burst = false             # no burst loss on this link (overrides an inherited burst)

Capacity and queue (``capacity``, ``queue``, ``medium`` in ``[faults]`` and ``[[faults.links]]``,
``--link-capacity``, ``--link-queue``, ``--link-medium``): :mod:`zenswarm.link.queue`; traces
(``[faults] trace``, ``--link-trace``): :mod:`zenswarm.link.trace`, loaded with the scenario's graph
by :func:`zenswarm.link.swarm.plan_for`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import replace
from typing import Any, TypeVar

from zenswarm.errors import ScenarioError
from zenswarm.link.names import KIND_ROLES, KINDS, check_exists, parse_process, parse_target, role_of
from zenswarm.link.plan import FaultPlan, GilbertElliott, LinkFaultSpec, Partition, parse_partition
from zenswarm.link.queue import queue_spec
from zenswarm.link.radio import RadioModel, parse_distance, parse_fade
from zenswarm.link.units import parse_duration, parse_loss
from zenswarm.schema import BurstTable, FadeTable, FaultsTable, LinkFaultsTable, PartitionTable, convert

__all__ = ["plan_from_cli", "plan_from_scenario", "plan_with_radio"]

T = TypeVar("T")


def _parsed(field: str, parse: Callable[..., T], text: Any, **kw: Any) -> T:
    """``parse(text)``; its ValueError as a :class:`ScenarioError` naming ``field`` (a flag or a
    scenario path)."""
    try:
        return parse(text, **kw)
    except ValueError as e:
        raise ScenarioError(field, str(e)) from None


def plan_from_cli(
    link_delay: str | None = None,
    link_jitter: str | None = None,
    link_loss: str | float | None = None,
    partitions: Iterable[str] = (),
    seed: int = 0,
    base: FaultPlan | None = None,
    n: int | None = None,
    link_capacity: str | None = None,
    link_queue: str | None = None,
    link_medium: str | None = None,
) -> FaultPlan:
    """The whole-swarm shortcuts ``--link-delay 50ms --link-jitter 10ms --link-loss 0.2
    --partition agent:2@10s-13s --link-capacity 20kB/s --link-queue 8 --link-medium sender`` as a plan.

    Given values replace the fields of ``base.default`` (a plan from the scenario; its per-link
    entries and partitions are kept); partitions are added. ``seed`` replaces ``base.seed``.
    ``n``, if given, is the number of UAVs: a partition of ``agent:<i>`` with i > n is refused.
    Raises :class:`ScenarioError` whose field is the flag (``--link-loss``).
    """
    base = base if base is not None else FaultPlan(seed=seed)
    d = base.default
    delay, jitter, loss = d.delay_s, d.jitter_s, d.loss
    if link_delay is not None:
        delay = _parsed("--link-delay", parse_duration, link_delay)
    if link_jitter is not None:
        jitter = _parsed("--link-jitter", parse_duration, link_jitter)
    if link_loss is not None:
        loss = _parsed("--link-loss", parse_loss, link_loss)
    parts = list(base.partitions)
    for text in partitions or ():
        parts.append(_parsed("--partition", parse_partition, text))
        check_exists("--partition", parts[-1].process_or_link, n)
    queue = queue_spec(("--link-capacity", "--link-queue", "--link-medium"), link_capacity, link_queue, link_medium, d.queue)
    default = LinkFaultSpec(delay, jitter, loss, d.burst, d.partitions, radio=d.radio, queue=queue)
    return FaultPlan(default, dict(base.per_link), seed, tuple(parts), base.trace, base.queues, base.hold_s)


def _duration_field(path: str, x: Any) -> float:
    if isinstance(x, (int, float)) and not isinstance(x, bool) and x == 0:
        return 0.0
    if not isinstance(x, str):
        raise ScenarioError(path, f"expected a duration string with a unit such as \"50ms\", got {x!r}")
    return _parsed(path, parse_duration, x)


def _burst_field(path: str, x: BurstTable | bool) -> GilbertElliott | None:
    if x is False:
        return None
    if not isinstance(x, BurstTable):
        raise ScenarioError(path, f"expected a table or false, got {x!r}")
    return GilbertElliott(x.p_good_to_bad, x.p_bad_to_good, x.loss_good, x.loss_bad)


def _partition_field(path: str, x: str | PartitionTable) -> Partition:
    if isinstance(x, str):
        return _parsed(path, parse_partition, x)
    target = _parsed(f"{path}.target", parse_target, x.target)
    t0 = _duration_field(f"{path}.start", x.start)
    if isinstance(x.end, str) and x.end.strip() in ("inf", "end"):
        t1 = math.inf
    else:
        t1 = _duration_field(f"{path}.end", x.end)
    if not t1 > t0:
        raise ScenarioError(f"{path}.end", f"must be after start ({x.end!r} <= {x.start!r})")
    return Partition(target, t0, t1)


def _endpoint_field(path: str, x: str) -> str:
    x = x.strip()
    if not x:
        raise ScenarioError(path, f"expected a process name or glob (plant, leader, agent:<i>, agent:*, *), got {x!r}")
    if any(c in x for c in "*?["):
        return x
    return _parsed(path, parse_process, x)


def _link_key(p: str, e: LinkFaultsTable, n_uavs: int | None) -> tuple[str, str, str]:
    """(src, dst, kind) of a ``[[faults.links]]`` entry at path ``p``, checked."""
    src = _endpoint_field(f"{p}.src", e.src)
    dst = _endpoint_field(f"{p}.dst", e.dst)
    check_exists(f"{p}.src", src, n_uavs)
    check_exists(f"{p}.dst", dst, n_uavs)
    kind = e.kind
    if kind not in KINDS and kind != "*":
        raise ScenarioError(f"{p}.kind", f"unknown kind {kind!r} (allowed: {', '.join(KINDS)}, *)")
    if kind != "*":
        want = KIND_ROLES[kind]
        for name, ep, role in (("src", src, want[0]), ("dst", dst, want[1])):
            if not any(c in ep for c in "*?[") and role_of(ep) != role:
                raise ScenarioError(f"{p}.{name}", f"a {kind!r} link goes {want[0]} -> {want[1]}; {ep!r} is not a {role}")
    if src == dst and not any(c in src for c in "*?["):
        raise ScenarioError(f"{p}.dst", f"a link needs two different processes, got {src!r} twice")
    return src, dst, kind


def _distance_field(path: str, x: Any, allow_inf: bool = True) -> float:
    if isinstance(x, bool) or not isinstance(x, (str, int, float)):
        raise ScenarioError(path, f"expected a distance such as \"1.5m\" (or metres), got {x!r}")
    return _parsed(path, parse_distance, x, allow_inf=allow_inf)


def _radio_field(p: str, e: FaultsTable | LinkFaultsTable, inherit: RadioModel | None) -> RadioModel | None:
    """The radio model of table ``e`` at ``p`` (keys ``range``, ``fade``), inheriting the rest."""
    if e.range is None and e.fade is None:
        return inherit
    base = inherit if inherit is not None else RadioModel()
    rng = base.range_m if e.range is None else _distance_field(f"{p}.range", e.range)
    r50, width = base.fade_50_m, base.fade_width_m
    if e.fade is False:
        r50, width = math.inf, 1.0
    elif isinstance(e.fade, FadeTable):
        r50 = _distance_field(f"{p}.fade.r50", e.fade.r50, allow_inf=False)
        width = _distance_field(f"{p}.fade.width", e.fade.width, allow_inf=False)
    elif e.fade is not None:
        raise ScenarioError(f"{p}.fade", f"expected a table {{ r50, width }} or false, got {e.fade!r}")
    return RadioModel(rng, r50, width)


def _spec(p: str, e: FaultsTable | LinkFaultsTable, inherit: LinkFaultSpec) -> LinkFaultSpec:
    """The link spec of table ``e`` at path ``p``; keys it does not set come from ``inherit``."""
    return LinkFaultSpec(
        inherit.delay_s if e.delay is None else _duration_field(f"{p}.delay", e.delay),
        inherit.jitter_s if e.jitter is None else _duration_field(f"{p}.jitter", e.jitter),
        inherit.loss if e.loss is None else float(e.loss),
        inherit.burst if e.burst is None else _burst_field(f"{p}.burst", e.burst),
        radio=_radio_field(p, e, inherit.radio),
        queue=queue_spec((f"{p}.capacity", f"{p}.queue", f"{p}.medium"), e.capacity, e.queue, e.medium, inherit.queue),
    )


def plan_from_scenario(section: FaultsTable | Mapping[str, Any] | None, seed: int, n_uavs: int | None = None) -> FaultPlan:
    """Build a plan from a scenario's ``[faults]`` table (``Scenario.faults``, or a dict validated
    by the schema, :class:`zenswarm.schema.FaultsTable`; ``None`` or ``{}``: no faults).

    Keys (all optional): ``delay``, ``jitter`` (duration strings), ``loss`` (probability),
    ``burst`` (table: ``p_good_to_bad``, ``p_bad_to_good`` required, ``loss_good`` = 0,
    ``loss_bad`` = 1), ``partitions`` (strings ``TARGET@START-END`` or tables ``{target, start,
    end}``), and ``[[faults.links]]`` entries with ``src``, ``dst`` (process names or globs,
    default ``*``), ``kind`` (``ref``, ``leader``, ``state``, ``cmd`` or ``*``) and any of
    ``delay``, ``jitter``, ``loss``, ``burst`` (``false`` to turn an inherited burst off); omitted
    fields inherit the ``[faults]`` values; later entries win. ``n_uavs``, if given, is the number
    of UAVs: naming ``agent:<i>`` with i > n is refused. Raises :class:`ScenarioError` naming the
    field, e.g. ``faults.links[0].loss``.
    """
    if section is None:
        return FaultPlan(seed=seed)
    t = section if isinstance(section, FaultsTable) else convert(section, FaultsTable, "faults")
    parts = [_partition_field(f"faults.partitions[{i}]", p) for i, p in enumerate(t.partitions)]
    for i, part in enumerate(parts):
        check_exists(f"faults.partitions[{i}]", part.process_or_link, n_uavs)
    default = _spec("faults", t, LinkFaultSpec(0.0, 0.0, 0.0, None))
    per: dict[tuple[str, str, str], LinkFaultSpec] = {}
    for n, entry in enumerate(t.links):
        p = f"faults.links[{n}]"
        key = _link_key(p, entry, n_uavs)
        if (entry.range is not None or entry.fade is not None) and key[2] in ("state", "cmd"):
            field_ = "range" if entry.range is not None else "fade"
            raise ScenarioError(f"{p}.{field_}", f"a {key[2]!r} link is on board (agent <-> its own autopilot), not radio")
        per.pop(key, None)
        per[key] = _spec(p, entry, default)
    hold = None
    if t.hold is not None:
        hold = _duration_field("faults.hold", t.hold)
        if not (math.isfinite(hold) and hold > 0):
            raise ScenarioError("faults.hold", f"the hold horizon must be a duration > 0 such as \"0.5s\", got {t.hold!r}")
    return FaultPlan(default, per, seed, tuple(parts), hold_s=hold)


def plan_with_radio(plan: FaultPlan, link_range: str | None = None, link_fade: str | None = None) -> FaultPlan:
    """The whole-swarm radio shortcuts ``--link-range 1.5m`` and ``--link-fade 1.2m,0.1m``
    (:mod:`zenswarm.link.radio`) applied to ``plan``: they replace the range / fall-off of its
    default spec, keeping the ``[[faults.links]]`` entries, as the other shortcuts do
    (:func:`plan_from_cli`). Raises :class:`ScenarioError` whose field is the flag."""
    if link_range is None and link_fade is None:
        return plan
    rng: float | None = None
    fade: tuple[float, float] | None = None
    if link_range is not None:
        rng = _parsed("--link-range", parse_distance, link_range)
    if link_fade is not None:
        fade = _parsed("--link-fade", parse_fade, link_fade)

    def with_radio(spec: LinkFaultSpec) -> LinkFaultSpec:
        r = spec.radio if spec.radio is not None else RadioModel()
        model = RadioModel(
            r.range_m if rng is None else rng,
            r.fade_50_m if fade is None else fade[0],
            r.fade_width_m if fade is None else fade[1],
        )
        return replace(spec, radio=model)

    return replace(plan, default=with_radio(plan.default), per_link=dict(plan.per_link))
