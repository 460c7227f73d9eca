"""Task families on any MuJoCo env: model parameters and action transforms drawn per episode.

:class:`TaskFamily` wraps a gymnasium MuJoCo env (gymnasium's HalfCheetah, Hopper, Walker2d, Ant,
gymnasium-robotics' Fetch and Franka envs, or your own ``MujocoEnv``) and turns it into a family
of tasks: at every reset it restores the model's defaults, resets the env, draws each named model
parameter and action transform from its distribution with the env's ``np_random`` (so
``reset(seed=...)`` fixes the whole episode, task included), writes the parameters into the
model and reports the draw in ``info["task"]``.

Parameters are named ``"<field>:<element>"`` with an optional component ``[k]``:

| Name                          | Model array (row of the element)     | Component without ``[k]`` | Valid values |
|-------------------------------|--------------------------------------|---------------------------|--------------|
| ``body_mass:<body>``          | ``body_mass``; ``body_inertia`` is scaled by the same factor | - | > 0 |
| ``geom_friction:<geom>``      | ``geom_friction`` (slide, spin, roll) | 0 (sliding)              | >= 0 |
| ``geom_size:<geom>``          | ``geom_size``                        | 0                         | > 0 |
| ``geom_pos:<geom>``           | ``geom_pos`` (in the body's frame)   | 0 (x)                     | any |
| ``geom_rgba:<geom>``          | ``geom_rgba``                        | 0 (red)                   | 0..1 |
| ``site_pos:<site>``           | ``site_pos`` (in the body's frame)   | 0 (x)                     | any |
| ``actuator_gear:<actuator>``  | ``actuator_gear``                    | 0                         | >= 0 |
| ``joint_damping:<joint>``     | ``dof_damping`` of every dof of the joint | -                    | >= 0 |
| ``gravity``                   | ``opt.gravity``                      | 2 (vertical)              | any |

Each model element has one name: the default component is written without ``[k]``
(``"gravity"``, ``"geom_friction:ffoot"``; ``"gravity[2]"`` and ``"geom_friction:ffoot[0]"`` are
refused with the canonical name in the message), and ``k`` is written in plain decimal digits
(``[1]``, not ``[01]``). Values outside the valid range (a negative mass or friction, a zero size)
make MuJoCo's simulation blow up or go silently wrong, so they are refused wherever they enter:
a distribution whose support leaves the range (when the family is built), a value in
``reset(options={"task": ...})`` (before anything changes) and :meth:`ModelParameters.set`.

An actuator without a name is found by the name of the joint (or tendon) it drives, and a geom
without a name by its body's name when it is the body's only geom. MuJoCo uses
the larger of two touching geoms' friction coefficients, so a family that lowers an object's
friction must lower its support's too. Growing a geom also grows its collision bounds
(``geom_rbound``, ``geom_aabb``) conservatively; moving one clears its ``geom_sameframe`` flag
(MuJoCo ignores ``geom_pos`` of a geom that the compiler marked as sitting at its body's frame).
Derived constants that MuJoCo computes when compiling (``body_subtreemass``, ``dof_invweight0``)
keep their default values.

The action transform maps the commanded action ``a`` to ``a'[dims] = gain * R(axis, rotation)
@ a[dims] + bias`` (the other entries pass unchanged), clipped to the action space. The reward
of the inner env is computed on ``a'``. ``R`` is a rotation about ``axis`` for three ``dims``,
and a planar rotation (counter-clockwise by the angle) for two.

Copies and pickles of a family simulate what they report: the parameters are written into the
model of the wrapped env the family holds now, which ``copy.deepcopy`` and ``pickle`` rebuild for
gymnasium's MuJoCo envs (``EzPickle``); a copy keeps the original's defaults and current task.

Example:
    >>> import gymnasium
    >>> from smcd_rl.integrations.task_family import ActionTransform, TaskFamily, Uniform
    >>> env = TaskFamily(
    ...     gymnasium.make("HalfCheetah-v5"),
    ...     params={"body_mass:torso": Uniform(5.0, 10.0), "joint_damping:bthigh": Uniform(3.0, 9.0)},
    ...     action=ActionTransform(gain=Uniform(0.5, 1.0)),
    ... )
    >>> obs, info = env.reset(seed=0)
    >>> sorted(info["task"])
    ['action:gain', 'body_mass:torso', 'joint_damping:bthigh']
    >>> 5.0 <= info["task"]["body_mass:torso"] <= 10.0
    True
    >>> obs, info = env.reset(options={"task": {"body_mass:torso": 7.0}})
    >>> info["task"]["body_mass:torso"], float(env.unwrapped.model.body("torso").mass[0])
    (7.0, 7.0)
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, SupportsFloat, runtime_checkable

import gymnasium
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from smcd_rl.envs.mujoco_setup import headless_mujoco, missing_extra

try:
    import mujoco
except ModuleNotFoundError as error:
    raise missing_extra(error, "mujoco", "smcd_rl.integrations.task_family (TaskFamily)") from error

__all__ = [
    "ActionTransform",
    "Choice",
    "Distribution",
    "Fixed",
    "LogUniform",
    "ModelParameters",
    "TaskFamily",
    "Uniform",
]

ACTION_NAMES = ("action:rotation", "action:gain", "action:bias")


@runtime_checkable
class Distribution(Protocol):
    """Anything that draws one float from a numpy ``Generator`` (the classes below, or your own)."""

    def sample(self, rng: np.random.Generator) -> float: ...


def _finite(value: Any, what: str) -> float:
    # float("1") and float(True) succeed; a string or a bool here is a mistake, not a number.
    not_a_number = isinstance(value, (str, bytes, bool, np.bool_)) or (isinstance(value, np.ndarray) and value.ndim > 0)
    try:
        if not_a_number:
            raise TypeError
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"{what} must be finite, got {value!r}")
    return number


@dataclass(frozen=True)
class _Interval:
    """A distribution on ``[low, high]``: the bounds are checked, and made floats, when it is built."""

    low: float
    high: float

    #: Whether ``low`` must also be positive (a log-uniform's logarithm needs it): a subclass says so
    #: in its bases, ``class LogUniform(_Interval, positive_low=True)``.
    _positive_low: ClassVar[bool] = False

    def __init_subclass__(cls, *, positive_low: bool = False, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._positive_low = positive_low

    def __post_init__(self) -> None:
        name = type(self).__name__
        low, high = _finite(self.low, f"{name} low"), _finite(self.high, f"{name} high")
        if not low <= high or (self._positive_low and not 0.0 < low):
            needs = "0 < low <= high" if self._positive_low else "low <= high"
            raise ValueError(f"{name} needs {needs}, got ({self.low}, {self.high})")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    def support(self) -> tuple[float, float]:
        """The smallest and largest value a draw can take."""
        return self.low, self.high


@dataclass(frozen=True)
class Uniform(_Interval):
    """Uniform on ``[low, high]``.

    Example:
        >>> import numpy as np
        >>> 2.0 <= Uniform(2.0, 4.5).sample(np.random.default_rng(0)) <= 4.5
        True
    """

    def sample(self, rng: np.random.Generator) -> float:
        """One draw."""
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True)
class LogUniform(_Interval, positive_low=True):
    """Log-uniform on ``[low, high]``, ``0 < low <= high``: as likely to halve as to double.

    Example:
        >>> import numpy as np
        >>> 0.5 <= LogUniform(0.5, 2.0).sample(np.random.default_rng(0)) <= 2.0
        True
    """

    def sample(self, rng: np.random.Generator) -> float:
        """One draw."""
        return float(np.exp(rng.uniform(np.log(self.low), np.log(self.high))))


@dataclass(frozen=True)
class Choice:
    """One of ``values``, uniformly.

    Example:
        >>> import numpy as np
        >>> Choice((0.0, 1.0)).sample(np.random.default_rng(0)) in (0.0, 1.0)
        True
    """

    values: tuple[float, ...]

    def __post_init__(self) -> None:
        if isinstance(self.values, (str, bytes)) or not isinstance(self.values, Iterable):
            raise ValueError(f"Choice takes a sequence of numbers, e.g. Choice((0.0, 1.0)), got {self.values!r}")
        values = tuple(_finite(v, "a Choice value") for v in self.values)
        if not values:
            raise ValueError("Choice needs at least one value")
        object.__setattr__(self, "values", values)

    def sample(self, rng: np.random.Generator) -> float:
        """One draw."""
        return self.values[int(rng.integers(len(self.values)))]

    def support(self) -> tuple[float, float]:
        """The smallest and largest value a draw can take."""
        return min(self.values), max(self.values)


@dataclass(frozen=True)
class Fixed:
    """Always ``value``; draws no random number.

    Example:
        >>> import numpy as np
        >>> Fixed(0.0).sample(np.random.default_rng(0))
        0.0
    """

    value: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "value", _finite(self.value, "Fixed value"))

    def sample(self, rng: np.random.Generator) -> float:
        """The value."""
        return self.value

    def support(self) -> tuple[float, float]:
        """The smallest and largest value a draw can take: the value."""
        return self.value, self.value


# field -> (object type, model array, component used without [k]; None: the whole row)
_FIELDS: dict[str, tuple[mujoco.mjtObj | None, str, int | None]] = {
    "body_mass": (mujoco.mjtObj.mjOBJ_BODY, "body_mass", None),
    "geom_friction": (mujoco.mjtObj.mjOBJ_GEOM, "geom_friction", 0),
    "geom_size": (mujoco.mjtObj.mjOBJ_GEOM, "geom_size", 0),
    "geom_pos": (mujoco.mjtObj.mjOBJ_GEOM, "geom_pos", 0),
    "geom_rgba": (mujoco.mjtObj.mjOBJ_GEOM, "geom_rgba", 0),
    "site_pos": (mujoco.mjtObj.mjOBJ_SITE, "site_pos", 0),
    "actuator_gear": (mujoco.mjtObj.mjOBJ_ACTUATOR, "actuator_gear", 0),
    "joint_damping": (mujoco.mjtObj.mjOBJ_JOINT, "dof_damping", None),
    "gravity": (None, "opt.gravity", 2),
}
# field -> (lowest valid value, whether the lowest is itself valid, highest valid value): the physical range.
_BOUNDS: dict[str, tuple[float, bool, float]] = {
    "body_mass": (0.0, False, math.inf),  # also keeps the inertia, scaled by the same factor, positive
    "geom_size": (0.0, False, math.inf),
    "geom_friction": (0.0, True, math.inf),
    "joint_damping": (0.0, True, math.inf),
    "actuator_gear": (0.0, True, math.inf),
    "geom_rgba": (0.0, True, 1.0),
}


def _bound_text(field: str) -> str:
    low, closed, high = _BOUNDS[field]
    if high == math.inf:
        return f"{'>=' if closed else '>'} {low:g}"
    return f"in [{low:g}, {high:g}]"


def _within(field: str, low: float, high: float) -> bool:
    """Whether every value in ``[low, high]`` is valid for ``field``."""
    if field not in _BOUNDS:
        return True
    bound_low, closed, bound_high = _BOUNDS[field]
    return (low >= bound_low if closed else low > bound_low) and high <= bound_high


# Arrays written besides the named ones (restored with them).
_DERIVED = {
    "body_mass": ("body_inertia",),
    "geom_size": ("geom_rbound", "geom_aabb"),
    "geom_pos": ("geom_sameframe",),
}
_OBJECT_WORD = {
    mujoco.mjtObj.mjOBJ_BODY: "body",
    mujoco.mjtObj.mjOBJ_GEOM: "geom",
    mujoco.mjtObj.mjOBJ_SITE: "site",
    mujoco.mjtObj.mjOBJ_ACTUATOR: "actuator",
    mujoco.mjtObj.mjOBJ_JOINT: "joint",
}
_NDOF = {0: 6, 1: 3, 2: 1, 3: 1}  # joint type (free, ball, slide, hinge) -> dofs


def _array(model: mujoco.MjModel, path: str) -> NDArray[Any]:
    owner: Any = model
    for part in path.split("."):
        owner = getattr(owner, part)
    return owner


def _names(model: mujoco.MjModel, objtype: mujoco.mjtObj, count: int) -> list[str]:
    return [name for i in range(count) if (name := mujoco.mj_id2name(model, objtype, i))]


@dataclass(frozen=True)
class _Entry:
    field: str
    array: str
    rows: tuple[int, ...]
    column: int | None


class ModelParameters:
    """Named parameters of a compiled MuJoCo model: read, write, and restore the defaults.

    The names are those of the module card (``"body_mass:object0"``, ``"geom_friction:table0"``,
    ``"geom_size:object0[1]"``, ``"gravity"``, ...). The defaults are the values the model has
    when this object is built; :meth:`restore` writes them back bit for bit, derived arrays included.

    Args:
        model: The compiled model (``env.unwrapped.model``); it is changed in place.
        names: Parameter names.

    Raises:
        ValueError: On an unknown field, element name or component (the message names the valid
            ones), or a second name for one model element (the message names the canonical one).

    Example:
        >>> import gymnasium
        >>> env = gymnasium.make("Hopper-v5")
        >>> params = ModelParameters(env.unwrapped.model, ["body_mass:torso", "gravity"])
        >>> params.defaults["gravity"]
        -9.81
        >>> params.set({"gravity": -5.0})
        >>> float(env.unwrapped.model.opt.gravity[2])
        -5.0
        >>> params.restore()
        >>> params.values() == params.defaults
        True
    """

    def __init__(self, model: mujoco.MjModel, names: Iterable[str]) -> None:
        self.model = model
        self._entries = {name: self._resolve(name) for name in names}
        arrays = {e.array for e in self._entries.values()}
        arrays |= {extra for e in self._entries.values() for extra in _DERIVED.get(e.field, ())}
        self._saved = {path: _array(model, path).copy() for path in sorted(arrays)}
        self._defaults = self.values()

    @property
    def names(self) -> tuple[str, ...]:
        """The parameter names, in the order given."""
        return tuple(self._entries)

    def values(self) -> dict[str, float]:
        """The model's current values."""
        return {name: self._get(entry) for name, entry in self._entries.items()}

    @property
    def defaults(self) -> dict[str, float]:
        """The model's values when this object was built."""
        return dict(self._defaults)

    def bind(self, model: mujoco.MjModel) -> ModelParameters:
        """The same parameters on another compile of the same model (a copy's), with these defaults.

        A copied or unpickled env (gymnasium's ``EzPickle`` rebuilds it) has a model of its own;
        this moves the parameter layer onto it, so that :meth:`set` writes where the copy simulates.

        Raises:
            ValueError: If ``model`` does not have the arrays of this object's model (another model).
        """
        for path, saved in self._saved.items():
            if _array(model, path).shape != saved.shape:
                raise ValueError(f"cannot bind the parameters to another model: {path} has another shape")
        bound = object.__new__(ModelParameters)
        bound.__dict__.update(self.__dict__)
        bound.model = model
        return bound

    def check(self, values: Mapping[str, Any], what: str = "value") -> dict[str, float]:
        """``values`` as floats, checked: known names, finite numbers in each parameter's valid range.

        Args:
            values: Values by parameter name.
            what: How the message names the values (``"options['task']"``).

        Raises:
            ValueError: On a name that is not one of :attr:`names`, a value that is not a finite
                number, or one outside the physical range of its kind (see the module card).
        """
        unknown = sorted(set(values) - set(self._entries))
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; valid: {list(self._entries)}")
        checked = {name: _finite(value, f"{what} of {name!r}") for name, value in values.items()}
        for name, value in checked.items():
            field = self._entries[name].field
            if not _within(field, value, value):
                raise ValueError(
                    f"{what} of {name!r} is {value:g}, but a {field} must be {_bound_text(field)}: "
                    "MuJoCo's simulation is not valid outside that range"
                )
        return checked

    def check_support(self, name: str, dist: Any) -> None:
        """Raise ValueError if ``dist`` (with a ``support()`` method) can draw an invalid value of ``name``.

        A distribution without ``support()`` is checked draw by draw instead (:meth:`check`).
        """
        support = getattr(dist, "support", None)
        if support is None:
            return
        low, high = support()
        field = self._entries[name].field
        if not _within(field, low, high):
            raise ValueError(
                f"the distribution of {name!r}, {dist!r}, draws values in [{low:g}, {high:g}], but a {field} "
                f"must be {_bound_text(field)}; choose a distribution within that range"
            )

    def set(self, values: Mapping[str, SupportsFloat]) -> None:
        """Write ``values`` into the model (names not given keep their current values).

        Raises:
            ValueError: As :meth:`check`; nothing is written.
        """
        checked = self.check(values)
        for name, value in checked.items():
            entry = self._entries[name]
            array = _array(self.model, entry.array)
            rows = list(entry.rows)
            if entry.column is None:
                array[rows] = value
            else:
                array[rows, entry.column] = value
            if entry.field == "geom_pos":
                self.model.geom_sameframe[rows] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE
        self._sync_derived({self._entries[name].field for name in checked})

    def restore(self) -> None:
        """Write the default values back (every array this object writes, bit for bit)."""
        for path, saved in self._saved.items():
            _array(self.model, path)[:] = saved

    def _sync_derived(self, fields: Collection[str]) -> None:
        model, saved = self.model, self._saved
        if "body_mass" in fields:
            rows = sorted({r for e in self._entries.values() if e.field == "body_mass" for r in e.rows})
            default = saved["body_mass"][rows]
            scale = np.divide(model.body_mass[rows], default, out=np.ones_like(default), where=default > 0)
            model.body_inertia[rows] = saved["body_inertia"][rows] * scale[:, None]
        if "geom_size" in fields:
            rows = sorted({r for e in self._entries.values() if e.field == "geom_size" for r in e.rows})
            default = saved["geom_size"][rows]
            ratio = np.divide(model.geom_size[rows], default, out=np.ones_like(default), where=default > 0)
            grow = np.maximum(ratio.max(axis=1), 1.0)
            model.geom_rbound[rows] = saved["geom_rbound"][rows] * grow
            model.geom_aabb[rows, 3:] = saved["geom_aabb"][rows, 3:] * grow[:, None]

    def _get(self, entry: _Entry) -> float:
        array = _array(self.model, entry.array)
        row = entry.rows[0]
        return float(array[row] if entry.column is None else array[row, entry.column])

    def _resolve(self, name: str) -> _Entry:
        if not isinstance(name, str):
            raise ValueError(f"parameter names are strings, got {name!r}")
        base, column = name, None
        if name.endswith("]") and "[" in name:
            base, _, index = name[:-1].rpartition("[")
            if not (index.isascii() and index.isdigit()):
                raise ValueError(f"parameter {name!r}: the component in [...] must be an integer")
            column = int(index)
            if str(column) != index:
                raise ValueError(f"parameter {name!r}: write the component as {base}[{column}] (one name per element)")
        field, colon, element = base.partition(":")
        if field not in _FIELDS:
            raise ValueError(f"parameter {name!r}: unknown field {field!r}; valid: {list(_FIELDS)}")
        objtype, path, default_column = _FIELDS[field]
        array = _array(self.model, path)
        if objtype is None:
            if colon:  # "gravity:" too: an empty element would be a second name for "gravity"
                raise ValueError(f"parameter {name!r}: {field!r} names no element (write {field!r} or {field}[k])")
            component = column if column is not None else (default_column or 0)
            if not 0 <= component < array.shape[0]:
                raise ValueError(f"parameter {name!r}: component must be in 0..{array.shape[0] - 1}")
            self._refuse_alias(name, base, column, default_column)
            return _Entry(field, path, (component,), None)
        rows = self._rows(name, field, objtype, element)
        width = array.shape[1] if array.ndim == 2 else 0
        if column is None:
            column = default_column if width else None
        if width == 0 and column is not None:
            raise ValueError(f"parameter {name!r}: {field!r} is a scalar and takes no component [k]")
        if column is not None and not 0 <= column < width:
            raise ValueError(f"parameter {name!r}: component must be in 0..{width - 1}")
        if name.endswith("]"):
            self._refuse_alias(name, base, column, default_column)
        return _Entry(field, path, rows, column)

    @staticmethod
    def _refuse_alias(name: str, base: str, column: int | None, default_column: int | None) -> None:
        """Refuse ``field:element[k]`` for the default component ``k``: ``field:element`` names it."""
        if column is not None and column == default_column and name != base:
            raise ValueError(
                f"parameter {name!r} is the default component; write {base!r} (one name per model element, "
                "so that a task reports each value once)"
            )

    def _rows(self, name: str, field: str, objtype: mujoco.mjtObj, element: str) -> tuple[int, ...]:
        model = self.model
        word = _OBJECT_WORD[objtype]
        index = mujoco.mj_name2id(model, objtype, element) if element else -1
        if objtype == mujoco.mjtObj.mjOBJ_ACTUATOR:
            valid = self._actuator_names()
            if index < 0 and element in valid:
                index = valid[element]
            valid_names = list(valid)
        elif objtype == mujoco.mjtObj.mjOBJ_GEOM:
            valid = self._geom_names()
            if index < 0 and element in valid:
                index = valid[element]
            valid_names = list(valid)
        else:
            count = {"body": model.nbody, "geom": model.ngeom, "site": model.nsite, "joint": model.njnt}[word]
            valid_names = _names(model, objtype, count)
        if index < 0:
            raise ValueError(f"parameter {name!r}: the model has no {word} named {element!r}; valid: {valid_names}")
        if field == "joint_damping":
            start = int(model.jnt_dofadr[index])
            return tuple(range(start, start + _NDOF[int(model.jnt_type[index])]))
        return (int(index),)

    def _geom_names(self) -> dict[str, int]:
        """Geom names, with an unnamed geom named by its body when it is the body's only geom."""
        model = self.model
        names = {name: g for g in range(model.ngeom) if (name := mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g))}
        for body in range(model.nbody):
            body_name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)
            geom = int(model.body_geomadr[body])
            single = model.body_geomnum[body] == 1 and not mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
            if body_name and single and body_name not in names:
                names[body_name] = geom
        return names

    def _actuator_names(self) -> dict[str, int]:
        """Actuator names, with unnamed actuators named by the joint or tendon they drive (if unique)."""
        model = self.model
        names: dict[str, int] = {}
        by_target: dict[str, list[int]] = {}
        for a in range(model.nu):
            own = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
            if own:
                names[own] = a
                continue
            trntype, target = int(model.actuator_trntype[a]), int(model.actuator_trnid[a, 0])
            objtype = {
                int(mujoco.mjtTrn.mjTRN_JOINT): mujoco.mjtObj.mjOBJ_JOINT,
                int(mujoco.mjtTrn.mjTRN_TENDON): mujoco.mjtObj.mjOBJ_TENDON,
            }.get(trntype)
            target_name = mujoco.mj_id2name(model, objtype, target) if objtype is not None else None
            if target_name:
                by_target.setdefault(target_name, []).append(a)
        for target_name, actuators in by_target.items():
            if len(actuators) == 1 and target_name not in names:
                names[target_name] = actuators[0]
        return names


@dataclass(frozen=True)
class ActionTransform:
    """An unknown map of the commanded action, drawn per episode: ``a'[dims] = gain * R a[dims] + bias``.

    Attributes:
        rotation: Angle (rad) of the rotation ``R``: about ``axis`` when ``dims`` has three
            entries (e.g. Fetch's commanded displacement, ``dims=(0, 1, 2)``), in the plane (counter-
            clockwise, from entry 0 towards entry 1) when it has two (a planar arm's command).
            `None`: no rotation.
        gain: Factor on the (rotated) entries; `None`: 1.
        bias: Added to each transformed entry; `None`: 0.
        dims: Action entries transformed, distinct non-negative ints; `None`: all (two or three
            for a rotation).
        axis: Rotation axis in the frame of ``a[dims]`` for a 3-D rotation, normalised; `None`:
            z, ``(0, 0, 1)``. A planar rotation takes no axis.

    Raises:
        TypeError: If ``rotation``, ``gain`` or ``bias`` has no ``sample(rng)`` method.
        ValueError: On non-integer, negative or repeated ``dims``, a rotation on other than two or
            three entries, or a bad ``axis``.

    Example:
        >>> t = ActionTransform(rotation=Fixed(np.pi / 2), dims=(0, 1, 2))
        >>> np.round(t.apply(np.array([1.0, 0.0, 0.0, 0.5]), {"action:rotation": np.pi / 2}), 6).tolist()
        [0.0, 1.0, 0.0, 0.5]
        >>> planar = ActionTransform(rotation=Fixed(np.pi / 2), dims=(0, 1))  # a 2-D command, turned 90 degrees
        >>> np.round(planar.apply(np.array([1.0, 0.0]), {"action:rotation": np.pi / 2}), 6).tolist()
        [0.0, 1.0]
    """

    rotation: Distribution | None = None
    gain: Distribution | None = None
    bias: Distribution | None = None
    dims: tuple[int, ...] | None = None
    axis: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        for what in ("rotation", "gain", "bias"):
            dist = getattr(self, what)
            if dist is not None and not isinstance(dist, Distribution):
                raise TypeError(f"ActionTransform.{what} must have a sample(rng) method, got {dist!r}")
        if self.axis is not None:
            axis = np.asarray(self.axis, dtype=np.float64) if _numbers(self.axis) else None
            if axis is None or axis.shape != (3,) or not np.all(np.isfinite(axis)) or not np.linalg.norm(axis) > 0:
                raise ValueError(f"axis must be a non-zero 3-vector, got {self.axis!r}")
            object.__setattr__(self, "axis", tuple(float(x) for x in axis))
        if self.dims is not None:
            # An ordered sequence: the order of dims sets the rotation's direction, which a set loses.
            ordered = isinstance(self.dims, Iterable) and not isinstance(self.dims, (set, frozenset, dict, str))
            dims = tuple(self.dims) if ordered else None
            if dims is None or not all(_is_int(d) and d >= 0 for d in dims):
                raise ValueError(
                    f"dims must be action indices (non-negative ints) in order, e.g. dims=(0, 1, 2); got {self.dims!r}"
                )
            if len(set(dims)) != len(dims):
                raise ValueError(f"dims must name each action entry once, got {self.dims!r}")
            object.__setattr__(self, "dims", tuple(int(d) for d in dims))
            self.check_size(len(dims))

    def check_size(self, count: int) -> None:
        """Raise ValueError if the transform cannot act on ``count`` action entries."""
        if self.rotation is None:
            return
        if count not in (2, 3):
            raise ValueError(
                f"a rotation acts on two action entries (a planar rotation) or three (a rotation about axis); "
                f"got {count} (dims={self.dims}): pass dims with two or three entries"
            )
        if count == 2 and self.axis is not None:
            raise ValueError(f"a planar rotation (two dims) takes no axis; got axis={self.axis}")

    def distributions(self) -> dict[str, Distribution]:
        """The drawn quantities, by name (``"action:rotation"``, ``"action:gain"``, ``"action:bias"``)."""
        pairs = zip(ACTION_NAMES, (self.rotation, self.gain, self.bias), strict=True)
        return {name: dist for name, dist in pairs if dist is not None}

    def apply(self, action: NDArray[Any], draw: Mapping[str, float]) -> NDArray[np.float64]:
        """The transformed action (not clipped) for the drawn values ``draw`` (missing names: identity)."""
        out = np.array(action, dtype=np.float64)
        dims = list(self.dims) if self.dims is not None else list(range(out.shape[-1]))
        self.check_size(len(dims))
        part = out[..., dims]
        if "action:rotation" in draw:
            angle = draw["action:rotation"]
            matrix = _rotation(self.axis or (0.0, 0.0, 1.0), angle) if len(dims) == 3 else _planar_rotation(angle)
            part = part @ matrix.T
        part = draw.get("action:gain", 1.0) * part + draw.get("action:bias", 0.0)
        out[..., dims] = part
        return out


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _numbers(values: Any) -> bool:
    return (
        isinstance(values, Iterable)
        and not isinstance(values, (str, bytes))
        and all(
            isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)) for v in values
        )
    )


def _rotation(axis: Sequence[float], angle: float) -> NDArray[np.float64]:
    """Rotation matrix about ``axis`` by ``angle`` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross


def _planar_rotation(angle: float) -> NDArray[np.float64]:
    """Counter-clockwise rotation of the plane by ``angle``."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


class TaskFamily(gymnasium.Wrapper[Any, Any, Any, Any], gymnasium.utils.RecordConstructorArgs):
    """A family of tasks on a MuJoCo env: named model parameters and an action transform drawn per episode.

    ``reset`` restores the model's defaults, resets the wrapped env, then draws every parameter
    (in the order of ``params``) and the action transform from the env's ``np_random``, writes
    them into the model, runs ``mj_forward`` and returns the env's observation (``_get_obs()``) and,
    for gymnasium's ``MujocoEnv``, reset info (``_get_reset_info()``) of the new model.
    The draw is in ``info["task"]`` of ``reset`` and ``step`` (Python floats, JSON-ready) and in
    :attr:`task`. ``close`` restores the defaults too.

    ``reset(options={"task": {...}})`` fixes the named quantities for that episode (the others are
    drawn as usual, from the same random numbers as without the option).

    ``copy.deepcopy`` and ``pickle`` give a family that writes into its own env's model (which
    gymnasium's MuJoCo envs rebuild on copy), with the original's defaults and current task.
    Made with a ``render_mode`` and no display, it chooses a headless MuJoCo backend
    (``MUJOCO_GL=egl``, see :func:`~smcd_rl.envs.mujoco_setup.headless_mujoco`).

    Args:
        env: A MuJoCo env (``env.unwrapped`` has ``model`` and ``data``), possibly wrapped by
            wrappers that leave its observations unchanged (``gymnasium.make``'s are fine).
        params: Distribution of each model parameter, by name (see the module card).
        action: Action transform; the action space must be a ``Box``.

    Raises:
        TypeError: If the env is not a MuJoCo env, a distribution has no ``sample`` method, or an
            action transform is given for a non-Box action space.
        ValueError: On an unknown parameter name or element (the message names the valid ones), a
            second name for one element, a distribution that draws values outside the parameter's
            physical range (a negative mass, friction, damping, ...), action dims outside the
            action, or if a wrapper between this one and the MuJoCo env changes the observation.

    Example:
        >>> import gymnasium
        >>> env = TaskFamily(gymnasium.make("Ant-v5"), params={"actuator_gear:hip_1": Choice((0.0, 150.0))})
        >>> obs, info = env.reset(seed=0, options={"task": {"actuator_gear:hip_1": 0.0}})
        >>> info["task"], float(env.unwrapped.model.actuator_gear[2, 0])  # hip_1 drives the unnamed actuator 2
        ({'actuator_gear:hip_1': 0.0}, 0.0)
        >>> env.close()  # restores the default gear
        >>> float(env.unwrapped.model.actuator_gear[2, 0])
        150.0
    """

    def __init__(
        self,
        env: gymnasium.Env[Any, Any],
        params: Mapping[str, Distribution] | None = None,
        action: ActionTransform | None = None,
    ) -> None:
        gymnasium.utils.RecordConstructorArgs.__init__(self, params=params, action=action)
        gymnasium.Wrapper.__init__(self, env)
        base: Any = env.unwrapped
        if not isinstance(getattr(base, "model", None), mujoco.MjModel) or not hasattr(base, "data"):
            raise TypeError(f"TaskFamily needs a MuJoCo env (unwrapped env with model and data), got {base!r}")
        self._check_wrappers(env)
        params = dict(params or {})
        for name, dist in params.items():
            if not isinstance(dist, Distribution):
                raise TypeError(f"the distribution of {name!r} must have a sample(rng) method, got {dist!r}")
        self._parameters = ModelParameters(base.model, params)
        for name, dist in params.items():
            self._parameters.check_support(name, dist)
        if action is not None:
            if not isinstance(env.action_space, spaces.Box):
                raise TypeError(f"an action transform needs a Box action space, got {env.action_space}")
            size = env.action_space.shape[-1]
            dims = action.dims if action.dims is not None else tuple(range(size))
            if any(not 0 <= d < size for d in dims):
                raise ValueError(f"action dims {dims} out of range for an action of size {size}")
            action.check_size(len(dims))
        self.action_transform = action
        self._distributions: dict[str, Distribution] = {**params, **(action.distributions() if action else {})}
        self._task: dict[str, float] = {}
        if env.render_mode is not None:
            headless_mujoco()  # before the first frame: gymnasium reads MUJOCO_GL when it makes the renderer

    @property
    def parameters(self) -> ModelParameters:
        """The model parameters, on the model of the env this family wraps now."""
        model = self.env.unwrapped.model  # type: ignore[attr-defined]
        if self._parameters.model is not model:  # a copy or unpickled family: its env has its own model
            self._parameters = self._parameters.bind(model)
        return self._parameters

    def __setstate__(self, state: dict[str, Any]) -> None:
        """After ``copy.deepcopy`` or unpickling: write the current task into the (rebuilt) env's model."""
        self.__dict__.update(state)
        parameters = self.parameters
        if parameters.names and self._task:
            parameters.set({name: self._task[name] for name in parameters.names})

    @staticmethod
    def _check_wrappers(env: gymnasium.Env[Any, Any]) -> None:
        layer = env
        while isinstance(layer, gymnasium.Wrapper):
            if (
                isinstance(layer, gymnasium.ObservationWrapper)
                or layer.observation_space != layer.env.observation_space
            ):
                raise ValueError(
                    f"TaskFamily recomputes the MuJoCo env's observation after changing the model; wrap the env "
                    f"before observation wrappers such as {type(layer).__name__}"
                )
            layer = layer.env

    @property
    def task_names(self) -> tuple[str, ...]:
        """Names of the drawn quantities: the parameters, then ``"action:rotation"``, ``"action:gain"``, ``"action:bias"``."""
        return tuple(self._distributions)

    @property
    def task(self) -> dict[str, float]:
        """The current episode's draw (empty before the first reset)."""
        return dict(self._task)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Restore the defaults, reset the env, draw and apply a task.

        Args:
            seed: Seed of the env's ``np_random`` (the draw comes from it).
            options: Passed to the env, except ``"task"``: a mapping of task names to values to
                use instead of draws in this episode.

        Raises:
            ValueError: On an unknown task name, a value that is not a finite number, or one
                outside its parameter's physical range; the env is left as it was. Also on a draw
                that is not finite, or outside the range, from a distribution of your own without
                ``support()``: the env is then reset with its defaults and reports no task.
        """
        options = dict(options or {})
        fixed = self._check_fixed(options.pop("task", None))
        parameters = self.parameters
        parameters.restore()
        self._task = {}  # the defaults, until a checked draw is written
        obs, info = self.env.reset(seed=seed, options=options or None)
        rng = self.env.unwrapped.np_random
        draw = {name: _finite(dist.sample(rng), f"the draw of {name!r}") for name, dist in self._distributions.items()}
        draw.update(fixed)
        if parameters.names:
            values = parameters.check({name: draw[name] for name in parameters.names}, what="the draw")
        self._task = draw
        if parameters.names:
            base: Any = self.env.unwrapped
            parameters.set(values)
            mujoco.mj_forward(base.model, base.data)
            obs = base._get_obs()
            if hasattr(base, "_get_reset_info"):  # gymnasium's MujocoEnv: reset info of the new model
                info = {**info, **base._get_reset_info()}
        return obs, {**info, "task": dict(draw)}

    def _check_fixed(self, fixed: Any) -> dict[str, float]:
        if fixed is None:
            return {}
        if not isinstance(fixed, Mapping):
            raise ValueError(f"options['task'] must be a mapping of task names to values, got {fixed!r}")
        unknown = sorted(set(fixed) - set(self._distributions))
        if unknown:
            raise ValueError(f"unknown task name(s) {unknown} in options['task']; valid: {list(self._distributions)}")
        checked = {name: _finite(value, f"options['task'][{name!r}]") for name, value in fixed.items()}
        parameters = self.parameters
        parameters.check({name: v for name, v in checked.items() if name in parameters.names}, what="options['task']")
        return checked

    def transform_action(self, action: Any) -> Any:
        """The action the env receives for a commanded ``action`` in this episode (clipped to the space).

        Raises:
            ValueError: If ``action`` does not have the shape of the action space.
        """
        space = self.env.action_space
        if isinstance(space, spaces.Box) and np.shape(action) != space.shape:
            raise ValueError(f"the action has shape {np.shape(action)}; this env takes actions of shape {space.shape}")
        if self.action_transform is None:
            return action
        assert isinstance(space, spaces.Box)
        moved = self.action_transform.apply(np.asarray(action), self._task)
        return np.clip(moved, space.low, space.high).astype(space.dtype)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Step the env with :meth:`transform_action` of ``action``; the reward as a float, ``info["task"]`` the draw.

        Raises:
            ValueError: If ``action`` does not have the shape of the action space.
        """
        obs, reward, terminated, truncated, info = self.env.step(self.transform_action(action))
        # A Python float: Fetch returns numpy float32 rewards, which stable-baselines3's checker refuses.
        return obs, float(reward), terminated, truncated, {**info, "task": dict(self._task)}

    def close(self) -> None:
        """Restore the model's defaults, then close the env."""
        self.parameters.restore()
        super().close()
