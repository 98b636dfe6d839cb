"""Build and validate a :class:`~ident.description.Mill` from a mapping.

The mill file's TOML (``../shared/spec/mill-config.md``) is parsed by
``ident.io.millfile``; this module turns the parsed mapping into the frozen
description, refusing anything the contract refuses with a
:class:`~ident.errors.MillFileError` that names the key and, through the
``locate`` callback the reader provides, the line.

The keys and tables known are exactly those of mill-config.md (:data:`_TABLE_KEYS`);
any other key or table is refused, with the known one it probably misspells
(:func:`difflib.get_close_matches`), since a misspelt optional key would otherwise
silently lose its value.
"""

from __future__ import annotations

import difflib
import hashlib
import math
from typing import Any, Callable, Mapping

from .description import (Bearing, Channel, Element, Load, Mass, Mill, Motor, Quantity,
                          StiffnessKind)
from .errors import MillFileError
from .units import QUANTITY_UNITS, normalize_unit

__all__ = ["mill_from_mapping", "mill_to_mapping", "apply_overrides", "Locator"]

#: ``locate(table, index, key) -> line`` where table is e.g. "element", index the
#: position of the ``[[element]]`` entry (None for plain tables), key the key or None.
Locator = Callable[[str, "int | None", "str | None"], "int | None"]


def _no_locate(table: str, index: int | None, key: str | None) -> int | None:
    return None


class _Ctx:
    """Carries the file path and locator so that every error names file, key and line."""

    def __init__(self, path: str | None, locate: Locator | None) -> None:
        self.path = path
        self.locate = locate or _no_locate

    def error(self, msg: str, table: str, index: int | None = None, key: str | None = None,
              label: str | None = None) -> MillFileError:
        name = table if index is None else f"{table}[{label if label else index}]"
        dotted = f"{name}.{key}" if key else name
        return MillFileError(msg, path=self.path, key=dotted, line=self.locate(table, index, key))


_TABLE_KEYS: dict[str, set[str]] = {
    "mill": {"name", "description"},
    "operation": {"motor_speed_rpm"},
    "mass": {"id", "label", "J"},
    "element": {"id", "label", "from", "to", "k", "c", "ratio", "gap", "gap_open", "radius",
                "gap_worn", "gap_critical", "k_gap", "stiffness", "knee", "k_after"},
    "load": {"masses", "share"},
    "motor": {"mass", "control", "kp", "ki", "torque_limit"},
    "bearing": {"id", "mesh", "ratio", "base_radius", "pressure_angle_deg", "shaft_mass",
                "k_bearing", "c_bearing", "clearance", "housing_mass", "k_housing",
                "k_housing_open", "housing_preload", "c_housing", "clearance_worn",
                "clearance_critical"},
    "channel": {"name", "quantity", "element", "bearing", "mass", "direction", "unit", "scale",
                "offset"},
}


def _closest(word: str, known: Any) -> str | None:
    """The known name ``word`` probably misspells (case-insensitive), or None."""
    by_lower = {k.lower(): k for k in known}
    near = difflib.get_close_matches(word.lower(), list(by_lower), n=1, cutoff=0.6)
    return by_lower[near[0]] if near else None


def _unknown(what: str, word: str, known: Any) -> str:
    near = _closest(word, known)
    if near is not None:
        return f"unknown {what} '{word}'; did you mean '{near}'?"
    return f"unknown {what} '{word}'; expected one of {sorted(known)}"


def _get(ctx: _Ctx, d: Mapping[str, Any], key: str, table: str, index: int | None = None,
         label: str | None = None, *, kind: type | tuple = (int, float), required: bool = True,
         default: Any = None) -> Any:
    if key not in d:
        if required:
            # name the missing key itself; the locator falls back to the table's header line
            raise ctx.error(f"required key '{key}' is missing", table, index, key, label)
        return default
    v = d[key]
    if kind in ((int, float), float):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ctx.error(f"must be a number. Got {v!r} instead", table, index, key, label)
        v = float(v)
        if not math.isfinite(v):
            raise ctx.error(f"must be finite. Got {v!r} instead", table, index, key, label)
        return v
    if not isinstance(v, kind):
        raise ctx.error(f"must be of type {getattr(kind, '__name__', kind)}. Got {v!r} instead",
                        table, index, key, label)
    return v


def _positive(ctx: _Ctx, v: float, table: str, index: int | None, key: str, label: str | None,
              *, allow_zero: bool = False) -> float:
    if v < 0 or (v == 0 and not allow_zero):
        need = "zero or positive" if allow_zero else "positive"
        raise ctx.error(f"must be {need}. Got {v!r} instead", table, index, key, label)
    return v


#: The top-level tables: plain ``[table]`` or arrays ``[[table]]``.
_ARRAY_TABLES = ("mass", "element", "bearing", "channel")
_PLAIN_TABLES = ("mill", "operation", "load", "motor")


def _check_unknown_keys(ctx: _Ctx, d: Mapping[str, Any], table: str, index: int | None,
                        label: str | None) -> None:
    """Refuse a key the table does not know (mill-config.md), naming the likely one."""
    known = _TABLE_KEYS[table]
    for k in d:
        if k not in known:
            raise ctx.error(_unknown("key", k, known), table, index, k, label)


def _check_unknown_tables(ctx: _Ctx, data: Mapping[str, Any]) -> None:
    """Refuse a top-level table or key mill-config.md does not define."""
    known = _PLAIN_TABLES + _ARRAY_TABLES
    for k, v in data.items():
        if k in known:
            continue
        if isinstance(v, Mapping) or (isinstance(v, list) and v and
                                      all(isinstance(x, Mapping) for x in v)):
            brackets = "[[{}]]" if isinstance(v, list) else "[{}]"
            near = _closest(k, known)
            hint = (f"did you mean {brackets.format(near)}?" if near is not None else
                    f"expected {[f'[{t}]' for t in _PLAIN_TABLES]} and "
                    f"{[f'[[{t}]]' for t in _ARRAY_TABLES]}")
            raise MillFileError(f"unknown table {brackets.format(k)}; {hint}", path=ctx.path,
                                key=k, line=ctx.locate(k, None, None))
        raise MillFileError(_unknown("top-level key", k, known) + " (every key belongs in a "
                            "table)", path=ctx.path, key=k, line=ctx.locate("", None, k))


def _list_of_tables(ctx: _Ctx, data: Mapping[str, Any], table: str, required: bool) -> list:
    v = data.get(table)
    if v is None:
        if required:
            raise ctx.error(f"at least one [[{table}]] is required", table)
        return []
    if not isinstance(v, list) or not all(isinstance(x, Mapping) for x in v):
        raise ctx.error(f"must be an array of tables [[{table}]]", table)
    return v


def _table(ctx: _Ctx, data: Mapping[str, Any], table: str, required: bool = True) -> Mapping:
    v = data.get(table)
    if v is None:
        if required:
            raise ctx.error(f"required table [{table}] is missing", table)
        return {}
    if not isinstance(v, Mapping):
        raise ctx.error(f"must be a table [{table}]", table)
    return v


def mill_from_mapping(data: Mapping[str, Any], *, path: str | None = None,
                      locate: Locator | None = None, sha256: str = "") -> Mill:
    """Validate a parsed mill file and return its immutable description.

    Parameters
    ----------
    data : mapping
        The parsed TOML.
    path : str, optional
        The file, named in errors.
    locate : callable, optional
        ``locate(table, index, key) -> line`` used to name lines in errors.
    sha256 : str
        Hash of the file's bytes, stored on the description.

    Returns
    -------
    Mill

    Raises
    ------
    MillFileError
        A missing required key, an unknown id, a non-positive inertia or
        stiffness, a self-loop, ``gap_open > gap``, shares not summing to 1, a
        disconnected graph or an unknown stiffness kind.
    """
    ctx = _Ctx(path, locate)
    _check_unknown_tables(ctx, data)
    mill_t = _table(ctx, data, "mill")
    _check_unknown_keys(ctx, mill_t, "mill", None, None)
    name = _get(ctx, mill_t, "name", "mill", kind=str)
    description = _get(ctx, mill_t, "description", "mill", kind=str, required=False, default="")
    op = _table(ctx, data, "operation")
    _check_unknown_keys(ctx, op, "operation", None, None)
    speed = _positive(ctx, _get(ctx, op, "motor_speed_rpm", "operation"), "operation", None,
                      "motor_speed_rpm", None)

    # masses ---------------------------------------------------------------------------
    masses: list[Mass] = []
    for i, m in enumerate(_list_of_tables(ctx, data, "mass", True)):
        mid = _get(ctx, m, "id", "mass", i, kind=str)
        _check_unknown_keys(ctx, m, "mass", i, mid)
        if mid in {x.id for x in masses}:
            raise ctx.error(f"duplicate mass id '{mid}'", "mass", i, "id", mid)
        J = _positive(ctx, _get(ctx, m, "J", "mass", i, mid), "mass", i, "J", mid)
        masses.append(Mass(id=mid, J=J, label=_get(ctx, m, "label", "mass", i, mid, kind=str,
                                                   required=False, default="")))
    mass_ids = {m.id for m in masses}

    def need_mass(v: str, table: str, i: int | None, key: str, label: str | None) -> str:
        if v not in mass_ids:
            raise ctx.error(f"unknown mass id '{v}'; known masses: {sorted(mass_ids)}", table, i,
                            key, label)
        return v

    # elements -------------------------------------------------------------------------
    elements: list[Element] = []
    for i, e in enumerate(_list_of_tables(ctx, data, "element", True)):
        eid = _get(ctx, e, "id", "element", i, kind=str)
        _check_unknown_keys(ctx, e, "element", i, eid)
        if eid in {x.id for x in elements} or eid in mass_ids:
            raise ctx.error(f"duplicate id '{eid}'", "element", i, "id", eid)
        frm = need_mass(_get(ctx, e, "from", "element", i, eid, kind=str), "element", i, "from", eid)
        to = need_mass(_get(ctx, e, "to", "element", i, eid, kind=str), "element", i, "to", eid)
        if frm == to:
            raise ctx.error(f"element joins mass '{frm}' to itself", "element", i, "to", eid)

        def num(key: str, default: float | None = None, *, required: bool = False,
                allow_zero: bool = True, positive: bool = True, _e=e, _i=i, _id=eid):
            v = _get(ctx, _e, key, "element", _i, _id, required=required, default=default)
            if v is not None and positive:
                _positive(ctx, v, "element", _i, key, _id, allow_zero=allow_zero)
            return v

        k = num("k", required=True, allow_zero=False)
        gap = num("gap", 0.0)
        gap_open = num("gap_open", 0.0)
        if gap_open > gap:
            raise ctx.error(f"gap_open ({gap_open}) must not exceed gap ({gap})", "element", i,
                            "gap_open", eid)
        kind_s = _get(ctx, e, "stiffness", "element", i, eid, kind=str, required=False,
                      default="linear")
        try:
            kind = StiffnessKind(kind_s)
        except ValueError:
            raise ctx.error(f"unknown stiffness kind {kind_s!r}; expected one of "
                            f"{[s.value for s in StiffnessKind]}", "element", i, "stiffness",
                            eid) from None
        knee = num("knee")
        k_after = num("k_after", allow_zero=False)
        if kind is not StiffnessKind.LINEAR:
            if knee is None or k_after is None:
                missing = "knee" if knee is None else "k_after"
                raise ctx.error(f"stiffness = '{kind.value}' needs '{missing}'", "element", i,
                                None, eid)
            if kind is StiffnessKind.SOFTENING and k_after >= k:
                raise ctx.error(f"softening needs k_after < k ({k_after} >= {k})", "element", i,
                                "k_after", eid)
            if kind is StiffnessKind.HARDENING and k_after <= k:
                raise ctx.error(f"hardening needs k_after > k ({k_after} <= {k})", "element", i,
                                "k_after", eid)
        gap_worn = num("gap_worn", 0.004, allow_zero=False)
        gap_critical = num("gap_critical", 0.008, allow_zero=False)
        if gap_critical < gap_worn:
            raise ctx.error(f"gap_critical ({gap_critical}) must not be below gap_worn "
                            f"({gap_worn})", "element", i, "gap_critical", eid)
        elements.append(Element(
            id=eid, from_=frm, to=to, k=k, c=num("c", 0.0), ratio=num("ratio", 1.0,
                                                                      allow_zero=False),
            gap=gap, gap_open=gap_open, k_gap=num("k_gap", 0.0), stiffness=kind, knee=knee,
            k_after=k_after, radius=num("radius", allow_zero=False), gap_worn=gap_worn,
            gap_critical=gap_critical,
            label=_get(ctx, e, "label", "element", i, eid, kind=str, required=False, default="")))
    element_ids = {e.id for e in elements}

    # connectivity (closed loops allowed) -----------------------------------------------
    adj: dict[str, set[str]] = {m: set() for m in mass_ids}
    for e in elements:
        adj[e.from_].add(e.to)
        adj[e.to].add(e.from_)
    seen = {masses[0].id}
    stack = [masses[0].id]
    while stack:
        for n in adj[stack.pop()]:
            if n not in seen:
                seen.add(n)
                stack.append(n)
    if seen != mass_ids:
        lonely = sorted(mass_ids - seen)
        idx = [m.id for m in masses].index(lonely[0])
        raise ctx.error(f"the driveline graph is disconnected: masses {lonely} are not linked "
                        f"to '{masses[0].id}' by any element", "mass", idx, "id", lonely[0])

    # load ------------------------------------------------------------------------------
    lt = _table(ctx, data, "load")
    _check_unknown_keys(ctx, lt, "load", None, None)
    lm = _get(ctx, lt, "masses", "load", kind=list)
    ls = _get(ctx, lt, "share", "load", kind=list)
    if not lm:
        raise ctx.error("must name at least one mass", "load", None, "masses")
    for m in lm:
        if not isinstance(m, str):
            raise ctx.error(f"must be mass ids. Got {m!r}", "load", None, "masses")
        need_mass(m, "load", None, "masses", None)
    if len(ls) != len(lm) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                      for x in ls):
        raise ctx.error(f"must be {len(lm)} numbers, one per load mass. Got {ls!r}", "load", None,
                        "share")
    if any(x < 0 for x in ls) or abs(sum(ls) - 1.0) > 1e-6:
        raise ctx.error(f"shares must be non-negative and sum to 1. Got {ls!r} (sum "
                        f"{sum(ls):.6g})", "load", None, "share")
    load = Load(masses=tuple(lm), share=tuple(float(x) for x in ls))

    # motor -----------------------------------------------------------------------------
    mt = _table(ctx, data, "motor")
    _check_unknown_keys(ctx, mt, "motor", None, None)
    control = _get(ctx, mt, "control", "motor", kind=str, required=False, default="pi_speed")
    if control != "pi_speed":
        raise ctx.error(f"unknown control {control!r}; expected 'pi_speed'", "motor", None,
                        "control")
    tl = _get(ctx, mt, "torque_limit", "motor", required=False)
    if tl is not None:
        _positive(ctx, tl, "motor", None, "torque_limit", None)
    motor = Motor(
        mass=need_mass(_get(ctx, mt, "mass", "motor", kind=str), "motor", None, "mass", None),
        kp=_positive(ctx, _get(ctx, mt, "kp", "motor"), "motor", None, "kp", None, allow_zero=True),
        ki=_positive(ctx, _get(ctx, mt, "ki", "motor"), "motor", None, "ki", None, allow_zero=True),
        control=control, torque_limit=tl)

    # bearings --------------------------------------------------------------------------
    bearings: list[Bearing] = []
    for i, b in enumerate(_list_of_tables(ctx, data, "bearing", False)):
        bid = _get(ctx, b, "id", "bearing", i, kind=str)
        _check_unknown_keys(ctx, b, "bearing", i, bid)
        if bid in {x.id for x in bearings} or bid in mass_ids or bid in element_ids:
            raise ctx.error(f"duplicate id '{bid}'", "bearing", i, "id", bid)
        mesh = _get(ctx, b, "mesh", "bearing", i, bid, kind=str)
        if mesh not in element_ids:
            raise ctx.error(f"unknown element id '{mesh}'", "bearing", i, "mesh", bid)

        def bnum(key: str, default: float | None = None, *, required: bool = False,
                 allow_zero: bool = True, _b=b, _i=i, _id=bid):
            v = _get(ctx, _b, key, "bearing", _i, _id, required=required, default=default)
            if v is not None:
                _positive(ctx, v, "bearing", _i, key, _id, allow_zero=allow_zero)
            return v

        bearings.append(Bearing(
            id=bid, mesh=mesh, ratio=bnum("ratio", 1.0, allow_zero=False),
            base_radius=bnum("base_radius", required=True, allow_zero=False),
            pressure_angle_deg=_get(ctx, b, "pressure_angle_deg", "bearing", i, bid,
                                    required=False, default=20.0),
            shaft_mass=bnum("shaft_mass", required=True, allow_zero=False),
            k_bearing=bnum("k_bearing", required=True, allow_zero=False),
            c_bearing=bnum("c_bearing", 0.0),
            clearance=bnum("clearance", required=True),
            housing_mass=bnum("housing_mass", required=True, allow_zero=False),
            k_housing=bnum("k_housing", required=True, allow_zero=False),
            k_housing_open=bnum("k_housing_open", allow_zero=False),
            housing_preload=bnum("housing_preload", math.inf, allow_zero=False),
            c_housing=bnum("c_housing", 0.0),
            clearance_worn=bnum("clearance_worn", 1.0e-3, allow_zero=False),
            clearance_critical=bnum("clearance_critical", 1.8e-3, allow_zero=False)))
    bearing_ids = {b.id for b in bearings}

    # channels --------------------------------------------------------------------------
    channels: list[Channel] = []
    for i, c in enumerate(_list_of_tables(ctx, data, "channel", False)):
        cname = _get(ctx, c, "name", "channel", i, kind=str)
        _check_unknown_keys(ctx, c, "channel", i, cname)
        if cname in {x.name for x in channels}:
            raise ctx.error(f"duplicate channel name '{cname}'", "channel", i, "name", cname)
        q_s = _get(ctx, c, "quantity", "channel", i, cname, kind=str)
        try:
            q = Quantity(q_s)
        except ValueError:
            raise ctx.error(f"unknown quantity {q_s!r}; expected one of "
                            f"{[x.value for x in Quantity]}", "channel", i, "quantity",
                            cname) from None
        unit = normalize_unit(_get(ctx, c, "unit", "channel", i, cname, kind=str))
        if unit not in QUANTITY_UNITS[q.value]:
            raise ctx.error(f"unit {unit!r} is not a {q.value} unit; expected one of "
                            f"{list(QUANTITY_UNITS[q.value])}", "channel", i, "unit", cname)
        target = {"torque": "element", "acceleration": "bearing", "speed": "mass"}[q.value]
        ref = _get(ctx, c, target, "channel", i, cname, kind=str)
        known = {"element": element_ids, "bearing": bearing_ids, "mass": mass_ids}[target]
        if ref not in known:
            raise ctx.error(f"unknown {target} id '{ref}'", "channel", i, target, cname)
        direction = _get(ctx, c, "direction", "channel", i, cname, kind=str, required=False)
        if q is Quantity.ACCELERATION:
            if direction not in ("vertical", "horizontal"):
                raise ctx.error(f"direction must be 'vertical' or 'horizontal'. Got {direction!r}",
                                "channel", i, "direction", cname)
        scale = _get(ctx, c, "scale", "channel", i, cname, required=False, default=1.0)
        if scale == 0:
            raise ctx.error("scale must not be zero", "channel", i, "scale", cname)
        channels.append(Channel(
            name=cname, quantity=q, unit=unit, direction=direction, scale=scale,
            offset=_get(ctx, c, "offset", "channel", i, cname, required=False, default=0.0),
            **{target: ref}))

    return Mill(name=name, description=description, masses=tuple(masses),
                elements=tuple(elements), load=load, motor=motor, motor_speed_rpm=speed,
                bearings=tuple(bearings), channels=tuple(channels), source=path, sha256=sha256)


def mill_to_mapping(mill: Mill) -> dict[str, Any]:
    """Return the mill-file mapping of a description (inverse of :func:`mill_from_mapping`)."""

    def clean(d: dict[str, Any]) -> dict[str, Any]:
        out = {}
        for k, v in d.items():
            if v is None or (isinstance(v, float) and math.isinf(v)):
                continue
            out[k] = v.value if hasattr(v, "value") and not isinstance(v, (int, float)) else v
        return out

    def element(e: Element) -> dict[str, Any]:
        d = {f.name: getattr(e, f.name) for f in e.__dataclass_fields__.values()}
        d["from"] = d.pop("from_")
        return clean(d)

    def plain(x: Any) -> dict[str, Any]:
        return clean({f.name: getattr(x, f.name) for f in x.__dataclass_fields__.values()})

    return {
        "mill": {"name": mill.name, "description": mill.description},
        "operation": {"motor_speed_rpm": mill.motor_speed_rpm},
        "mass": [plain(m) for m in mill.masses],
        "element": [element(e) for e in mill.elements],
        "load": {"masses": list(mill.load.masses), "share": list(mill.load.share)},
        "motor": plain(mill.motor),
        "bearing": [plain(b) for b in mill.bearings],
        "channel": [plain(c) for c in mill.channels],
    }


def apply_overrides(mill: Mill, overrides: Mapping[str, Any]) -> Mill:
    """Return ``mill`` with ``{"ID.KEY": value}`` overrides applied and revalidated.

    ``ID`` is a mass, element, bearing or channel id, or one of ``mill``,
    ``operation``, ``motor``, ``load``.

    Raises
    ------
    MillFileError
        Unknown id or key, or a value the mill file would refuse.
    """
    data = mill_to_mapping(mill)
    for dotted, value in overrides.items():
        if "." not in dotted:
            raise MillFileError(f"override must look like ID.KEY=VALUE. Got {dotted!r}",
                                key=dotted)
        ident, key = dotted.split(".", 1)
        target = None
        if ident in ("mill", "operation", "motor", "load"):
            target = data[ident]
            table = ident
        else:
            for table in ("mass", "element", "bearing", "channel"):
                idkey = "name" if table == "channel" else "id"
                for entry in data[table]:
                    if entry.get(idkey) == ident:
                        target = entry
                        break
                if target is not None:
                    break
        if target is None:
            ids = [*_PLAIN_TABLES, *(e.get("name" if t == "channel" else "id")
                                     for t in _ARRAY_TABLES for e in data[t])]
            near = _closest(ident, ids)
            hint = f"; did you mean '{near}'?" if near is not None else ""
            raise MillFileError(f"unknown id '{ident}' in override {dotted!r}{hint}",
                                key=dotted)
        if key not in _TABLE_KEYS[table]:
            near = _closest(key, _TABLE_KEYS[table])
            hint = f"; did you mean '{near}'?" if near is not None else ""
            raise MillFileError(f"unknown key '{key}' for a {table}; expected one of "
                                f"{sorted(_TABLE_KEYS[table])}{hint}", key=dotted)
        target[key] = value
    tag = hashlib.sha256((mill.sha256 + repr(sorted(overrides.items()))).encode()).hexdigest()
    return mill_from_mapping(data, path=mill.source, sha256=tag)
