"""Scenario overrides by dotted path: ``timing.time_limit_s``, ``controller.kp``,
``obstacles[0].radius``, the same keys everywhere they are taken (``api.fly(overrides=)``,
``zenswarm sim/up --set KEY=VALUE``, ``zenswarm sweep --grid KEY=...``).

A document (the scenario's TOML as nested dicts) gets each value set at its path, missing tables
created (the schema then refuses keys that are not fields); the result is validated as a file
would be, the plug-ins' parameters included (:func:`zenswarm.scenario.plugins.check_selection`). Every
error an override causes is an :class:`OverrideError` naming the field and the override.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Mapping
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.scenario.config import Scenario, scenario_from_dict

__all__ = ["OverrideError", "apply", "parse_assignment", "validated", "copy_document", "check_plugins", "load_file"]


class OverrideError(ScenarioError):
    """An override's path does not name a scenario field, or its value is refused.

    ``field`` is the dotted path of the scenario field (as in :class:`ScenarioError`);
    ``override`` the key given that caused it."""

    def __init__(self, field: str, message: str, override: str) -> None:
        super().__init__(field, message)
        self.override = override


def copy_document(x: Any) -> Any:
    """A deep copy of a TOML document (dicts and lists)."""
    if isinstance(x, dict):
        return {k: copy_document(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [copy_document(v) for v in x]
    return x


def _tokens(path: str) -> list[str | int]:
    """``obstacles[0].radius`` -> ["obstacles", 0, "radius"]; OverrideError on bad syntax."""
    if not isinstance(path, str) or not re.fullmatch(r"[A-Za-z_][\w-]*(\[\d+\]|\.[A-Za-z_][\w-]*)*", path):
        raise OverrideError(str(path), "not a dotted path to a scenario field (e.g. timing.time_limit_s, obstacles[0].radius)", str(path))
    return [t if t else int(i) for t, i in re.findall(r"([A-Za-z_][\w-]*)|\[(\d+)\]", path)]


def _plain(value: Any) -> Any:
    """A Python value as TOML would hold it: tuples and arrays as lists, numpy scalars as numbers."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def set_path(doc: dict[str, Any], path: str, value: Any) -> None:
    """Set ``value`` at ``path`` in the document, creating missing tables (the schema then
    refuses keys that are not fields). A path into a list must name an existing element."""
    toks = _tokens(path)
    cur: Any = doc
    for pos, (tok, nxt) in enumerate(zip(toks, [*toks[1:], None], strict=True)):
        here = "".join(f"[{t}]" if isinstance(t, int) else f".{t}" for t in toks[: pos + 1]).lstrip(".")
        last = nxt is None
        if isinstance(tok, int):
            if not isinstance(cur, list) or tok >= len(cur):
                n = len(cur) if isinstance(cur, list) else 0
                raise OverrideError(here, f"no element {tok} (the scenario has {n})", path)
            if last:
                cur[tok] = _plain(value)
            else:
                cur = cur[tok]
            continue
        if not isinstance(cur, dict):
            raise OverrideError(here, "is not a table", path)
        if last:
            cur[tok] = _plain(value)
        else:
            if tok not in cur:
                cur[tok] = [] if isinstance(nxt, int) else {}
            cur = cur[tok]


def _related(a: str, b: str) -> bool:
    """One dotted path is the other or lies below it."""
    return a == b or a.startswith(b + ".") or a.startswith(b + "[") or b.startswith(a + ".") or b.startswith(a + "[")


def _blame(e: ScenarioError, overrides: Mapping[str, Any]) -> OverrideError:
    culprit = next((p for p in overrides if _related(e.field, str(p))), None)
    if culprit is None:  # a cross-field check (leader.k_rep_max >= k_rep_min, ...)
        given = ", ".join(map(str, overrides))
        return OverrideError(e.field, f"{e.message} (after the overrides {given})", given)
    return OverrideError(e.field, e.message, str(culprit))


def apply(doc: dict[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of ``doc`` with every override set (in order); OverrideError on a bad path."""
    out: dict[str, Any] = copy_document(doc)
    for path, value in overrides.items():
        set_path(out, path, value)
    return out


def validated(doc: dict[str, Any], overrides: Mapping[str, Any], plugins: bool = True) -> Scenario:
    """The scenario of ``doc`` with ``overrides`` applied, converted once and validated, the
    plug-ins' names and parameters too (``plugins``). An error of the scenario itself is a
    :class:`ScenarioError`; every error an override caused is an :class:`OverrideError` (told
    apart, only when there is an error, by converting ``doc`` without the overrides)."""
    from zenswarm.scenario.plugins import check_selection

    if not overrides:
        sc = scenario_from_dict(copy_document(doc))
        if plugins:
            check_selection(sc)
        return sc
    new = apply(doc, overrides)
    try:
        sc = scenario_from_dict(new)
        if plugins:
            check_selection(sc)
    except OverrideError:
        raise
    except ScenarioError as e:
        validated(doc, {}, plugins)  # the scenario's own error: raised as such
        raise _blame(e, overrides) from None
    return sc


def parse_assignment(text: str, flag: str = "--set") -> tuple[str, Any]:
    """``KEY=VALUE`` of the command line: VALUE read as a TOML value (``0.5``, ``[1, 2, 3]``,
    ``true``, ``"text"``), else taken as a string (``agents.controller=my_pkg.ctl:Mine``; also
    ``nan`` and ``inf``, which no field takes as a number).
    ScenarioError naming ``flag`` when there is no ``=`` or no key."""
    key, eq, raw = text.partition("=")
    key, raw = key.strip(), raw.strip()
    if not eq or not key:
        raise ScenarioError(flag, f"expected KEY=VALUE (e.g. controller.kp=[4,4,5]), got {text!r}")
    _tokens_checked(key, flag)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    if isinstance(value, float) and not np.isfinite(value) and raw.lstrip("+-").isalpha():
        value = raw  # TOML's nan and inf: hardly ever meant; a field that is a number refuses the text
    return key, value


def _tokens_checked(key: str, flag: str) -> None:
    try:
        _tokens(key)
    except OverrideError as e:
        raise OverrideError(e.field, f"{flag} {key}: {e.message}", key) from None


def check_plugins(
    sc: Scenario, overrides: Mapping[str, Any], controller_field: str | None = None, planner_field: str | None = None,
    flag: str = "--set", plant_field: str | None = None,
) -> None:
    """:func:`zenswarm.scenario.plugins.check_selection` of ``sc``; an error in a field an override set is
    an :class:`OverrideError` naming ``flag KEY`` (the override)."""
    from zenswarm.scenario.plugins import check_selection

    try:
        check_selection(sc, controller_field, planner_field, plant_field)
    except OverrideError:
        raise
    except ScenarioError as e:
        culprit = next((p for p in overrides if _related(e.field, str(p))), None)
        if culprit is None:
            raise
        raise OverrideError(e.field, f"{e.message} (from {flag} {culprit})", str(culprit)) from None


def load_file(path: Any, overrides: Mapping[str, Any]) -> Scenario:
    """A scenario file (:func:`zenswarm.scenario.config.load_scenario`: its errors, its relative trace
    path) with ``overrides`` applied and validated (not the plug-ins: :func:`check_plugins`)."""
    from zenswarm.scenario.config import read_document, scenario_of_document, trace_beside

    doc = read_document(path)  # parsed once (a large scenario's TOML is its slowest part)
    sc = scenario_of_document(doc, path)  # the file's own errors first, as such
    if not overrides:
        return sc
    return trace_beside(validated(doc, overrides, plugins=False), path)
