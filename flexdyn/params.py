"""Named access to a chain's physical parameters: `'link1.EI'`, `'joint2.damping'`,
`'hub1.inertia'`, `'payload.mass'`, `'link1.damping_ratio[0]'`, `'gravity[1]'`,
`'motor1.resistance'` (a joint's `DCMotor`, if it has one).

Numbering is 1-based from the base, as in the papers. These names are the
vocabulary of experiment files and of fits (`identify`): any parameter listed by
`parameter_names` can be read, replaced (functionally, `with_parameters`) and
differentiated.
"""

from __future__ import annotations

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .chain import Chain
from .motor import DCMotor
from .parts import ElasticJoint, FlexibleLink, Hub, Payload, RigidJoint, RigidLink

#: Fields that are physical parameters, per part type, with their SI unit.
PARAMETER_FIELDS: dict[type, dict[str, str]] = {
    RigidLink: {"length": "m", "mass": "kg", "com": "m", "inertia": "kg m^2", "drag": "kg/m^2"},
    FlexibleLink: {
        "length": "m",
        "rho": "kg/m",
        "EI": "N m^2",
        "damping_ratio": "1",
        "sqrt_stiffness_damping": "kg^0.5",
        "drag": "kg/m^2",
    },
    RigidJoint: {"damping": "N m s/rad", "rotor_inertia": "kg m^2", "gear_ratio": "1", "coulomb": "N m"},
    ElasticJoint: {
        "stiffness": "N m/rad",
        "rotor_inertia": "kg m^2",
        "gear_ratio": "1",
        "damping": "N m s/rad",
        "spring_damping": "N m s/rad",
        "coulomb": "N m",
        "backlash": "rad",
    },
    Hub: {"mass": "kg", "inertia": "kg m^2"},
    Payload: {"mass": "kg", "inertia": "kg m^2"},
    DCMotor: {
        "resistance": "ohm",
        "torque_constant": "N m/A",
        "efficiency": "1",
        "inductance": "H",
        "viscous": "N m s/rad",
        "coulomb": "N m",
        "voltage_limit": "V",
    },
}

#: Optional fields (`None` on a part: the term is absent and so is the parameter).
OPTIONAL = {"drag", "coulomb", "backlash"}

#: Parameters that may take any sign (all others are >= 0 and are fitted in log space).
SIGNED = {"com", "gravity"}

_NAME = re.compile(
    r"^(?P<part>link|joint|hub|motor)(?P<index>\d+)\.(?P<field>\w+)(\[(?P<k>\d+)\])?$|"
    r"^(?P<payload>payload)\.(?P<pfield>\w+)$|^(?P<gravity>gravity)\[(?P<g>[01])\]$"
)


def _part(chain: Chain, kind: str, index: int):
    parts = {"link": chain.links, "joint": chain.joints, "hub": chain.hubs, "motor": chain.motors}[kind]
    return parts[index - 1]


def parameter_names(chain: Chain) -> list[str]:
    """Every named scalar parameter of `chain`, in a stable order."""
    names = []
    for kind, parts in (("link", chain.links), ("joint", chain.joints), ("hub", chain.hubs), ("motor", chain.motors)):
        for i, part in enumerate(parts, start=1):
            if part is None:  # a joint without a motor
                continue
            for field in PARAMETER_FIELDS[type(part)]:
                value = getattr(part, field)
                if value is None:
                    continue
                if np.ndim(value) == 0:
                    names.append(f"{kind}{i}.{field}")
                else:
                    names.extend(f"{kind}{i}.{field}[{k}]" for k in range(np.shape(value)[0]))
    names.extend(f"payload.{f}" for f in PARAMETER_FIELDS[Payload])
    names.extend(["gravity[0]", "gravity[1]"])
    return names


def _locate(chain: Chain, name: str):
    """(getter of the leaf array, index into it or None, unit, signed) for `name`."""
    m = _NAME.match(name)
    if m is None:
        raise _unknown(chain, name)
    if m["gravity"]:
        return (lambda c: c.gravity), int(m["g"]), "m/s^2", True
    if m["payload"]:
        field = m["pfield"]
        if field not in PARAMETER_FIELDS[Payload]:
            raise _unknown(chain, name)
        return (lambda c: getattr(c.payload, field)), None, PARAMETER_FIELDS[Payload][field], False
    kind, index, field = m["part"], int(m["index"]), m["field"]
    n = len(chain.links)
    if not 1 <= index <= n:
        raise _unknown(chain, name)
    part = _part(chain, kind, index)
    if part is None:
        raise UnknownParameterError(
            f"parameter {name!r}: joint {index} has no motor (Chain(..., motors=[...]) gives joint {index} a "
            f"flexdyn.DCMotor); this chain has: {', '.join(parameter_names(chain))}"
        )
    fields = PARAMETER_FIELDS[type(part)]
    if field not in fields:
        raise _unknown(chain, name)
    if getattr(part, field) is None:
        # (say which term is missing and how to add it, not a plain KeyError)
        if field not in OPTIONAL:  # a motor's inductance or voltage limit: no neutral value to add it at
            raise UnknownParameterError(
                f"parameter {name!r}: {kind} {index} has no {field} ({type(part).__name__}({field}=None)); "
                f"build it with {type(part).__name__}(..., {field}=<a value> [{fields[field]}]) to make it a parameter"
            )
        raise UnknownParameterError(
            f"parameter {name!r}: {kind} {index} has no {field} term ({type(part).__name__}({field}=None)); "
            f"build it with {type(part).__name__}(..., {field}=0.0), or add it with "
            f"flexdyn.with_optional_terms(chain, [{name!r}]), to make it a parameter"
        )
    k = None if m["k"] is None else int(m["k"])
    ndim = np.ndim(getattr(part, field))
    if (k is None) != (ndim == 0) or (k is not None and k >= np.shape(getattr(part, field))[0]):
        raise _unknown(chain, name)
    return (lambda c: getattr(_part(c, kind, index), field)), k, fields[field], field in SIGNED


def absent_optional_term(chain: Chain, name: str) -> bool:
    """True when `name` is an optional term (`OPTIONAL`: a link's `drag`, a joint's
    `coulomb`, an elastic joint's `backlash`) of a part of `chain` that does not have it
    (the field is None), i.e. `with_optional_terms` would make it a parameter."""
    m = _NAME.match(name)
    if m is None or not m["part"] or m["k"] is not None or m["field"] not in OPTIONAL:
        return False
    index = int(m["index"])
    if not 1 <= index <= len(chain.links):
        return False
    part = _part(chain, m["part"], index)
    return part is not None and m["field"] in PARAMETER_FIELDS[type(part)] and getattr(part, m["field"]) is None


def with_optional_terms(chain: Chain, names) -> Chain:
    """`chain` with the optional terms `names` (`"joint2.coulomb"`, `"link1.drag"`,
    `"joint1.backlash"`) present at 0.0, their neutral value: the same equations, now with
    these parameters (set them with `with_parameters`). Names already present are left as
    they are; any other name is an `UnknownParameterError`."""
    for name in names:
        if absent_optional_term(chain, name):
            m = _NAME.match(name)
            kind, index, field = m["part"], int(m["index"]), m["field"]
            chain = eqx.tree_at(
                lambda c: getattr(_part(c, kind, index), field),
                chain,
                jnp.asarray(0.0, dtype=float),
                is_leaf=lambda x: x is None,
            )
        else:
            _locate(chain, name)  # present: fine; anything else: named
    return chain


class UnknownParameterError(KeyError, ValueError):
    """A parameter name the chain does not have. A `KeyError` (a lookup by name) and a
    `ValueError` (as `identify.make_problem` raises for the same mistake); its message is
    shown as written, not quoted as `KeyError`'s is."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


def closest_name(name: str, names) -> str | None:
    """The entry of `names` that `name` most likely meant: the same but for case
    (`link1.ei` -> `link1.EI`), else the closest spelling (`difflib`, ratio >= 0.8), else None."""
    import difflib

    names = list(names)
    folded = [n for n in names if n.lower() == name.lower()]
    if folded:
        return folded[0]
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.8)
    return close[0] if close else None


def did_you_mean(name: str, names) -> str:
    """` (did you mean 'link1.EI'?)` when `closest_name` finds one, else ''."""
    near = closest_name(name, names)
    return f" (did you mean {near!r}?)" if near is not None and near != name else ""


def _unknown(chain: Chain, name: str) -> UnknownParameterError:
    names = parameter_names(chain)
    return UnknownParameterError(
        f"unknown parameter {name!r}{did_you_mean(name, names)}; this chain has: {', '.join(names)}"
    )


def parameter_unit(chain: Chain, name: str) -> str:
    """SI unit of a named parameter."""
    return _locate(chain, name)[2]


def is_signed(chain: Chain, name: str) -> bool:
    """True for parameters that may be negative (`com`, gravity components)."""
    return _locate(chain, name)[3]


def get_parameter(chain: Chain, name: str):
    """The value of a named parameter (a JAX scalar)."""
    getter, k, _, _ = _locate(chain, name)
    value = getter(chain)
    return value if k is None else value[k]


def with_parameters(chain: Chain, values: dict) -> Chain:
    """A copy of `chain` with the named parameters replaced (values may be traced, so
    this is differentiable and vmappable)."""
    for name, value in values.items():
        getter, k, _, _ = _locate(chain, name)
        value = jnp.asarray(value, dtype=float)
        if np.ndim(value) != 0:
            raise ValueError(f"parameter {name!r}: expected a scalar, got shape {np.shape(value)}")
        if k is None:
            chain = eqx.tree_at(getter, chain, value)
        else:
            chain = eqx.tree_at(getter, chain, getter(chain).at[k].set(value))
        _recheck(chain, name)
    return chain


def _recheck(chain: Chain, name: str) -> None:
    """Re-run the validation of the part a parameter belongs to (eqx.tree_at bypasses
    __init__): concrete values are checked now, traced ones inside `assemble`."""
    m = _NAME.match(name)
    if m["gravity"]:
        g = chain.gravity
        if not isinstance(g, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(g))):
            raise ValueError(f"{name}: expected a finite value [m/s^2], got {np.asarray(g)}")
        return
    part = chain.payload if m["payload"] else _part(chain, m["part"], int(m["index"]))
    part.__check_init__()
