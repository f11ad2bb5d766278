"""The teacher backends as data (eq:teacher-prediction), the one registry of their names: one row per backend
with its class, the ``teacher:`` settings it requires and its capabilities.  Pure Python, so the params
schema, the report and ``label --help`` read it without starting torch; :func:`teacher_class` imports a
backend's class (a :class:`pipeline.teachers.base.Teacher`) when it is used.

Plug-ins: an installed package adds a row through the entry-point group :data:`TEACHER_GROUP` (label
formats: :data:`FORMAT_GROUP`), loaded by :func:`plugin` the first time a name is not in the table
(docs/pipeline.md, "How to extend")."""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata

from pipeline.runtime.errors import InputError, Option

SIMULATED, SAM3, IMPORTED = "simulated", "sam3", "imported"
#: the entry-point groups of plug-ins: ``name = "module:OBJECT"``, a :class:`TeacherSpec` / a ``LabelFormat``
TEACHER_GROUP, FORMAT_GROUP = "geodistill.teachers", "geodistill.label_formats"


@dataclasses.dataclass(frozen=True)
class TeacherSpec:
    """One backend: its class (``"module:Class"``, imported when used, or the class), the ``--backend`` help,
    the ``teacher.*`` settings it requires, and its capabilities.

    ``simulator``: a SIMULATOR of a teacher that reads the reference masks (never a real teacher's labels);
    ``use_cache``: its answers go through the teacher cache (False where reading them is as cheap);
    ``note``: the report's sentence on its numbers (None: it names the backend); ``check``: a
    ``"module:function"`` called as ``f(value, option)`` on its first setting when a command option gives it;
    ``folder``: the help of the command option (``--checkpoint``) that sets its first setting, a folder, and
    implies this backend; ``options``: the pydantic model (or ``"module:Model"``) of its ``teacher.options``
    (None: it takes none); ``distribution``: a plug-in's ``"name version"``, set when it is loaded (part of
    the teacher fingerprint: DVC and the code version do not see a plug-in's code)."""

    teacher: str | type
    description: str
    settings: tuple[str, ...] = ()
    simulator: bool = False
    use_cache: bool = True
    note: str | None = None
    check: str | None = None
    folder: str | None = None
    options: str | type | None = None
    distribution: str | None = None


#: name -> backend, in ``--backend``'s order; extend with :func:`register_teacher`
TEACHER_TABLE: dict[str, TeacherSpec] = {
    SIMULATED: TeacherSpec(
        "pipeline.teachers.simulated:SimulatedFoundationTeacher",
        "a SIMULATOR of foundation-model errors (synthetic benchmark; needs --reference-masks)", simulator=True,
        note="Teacher = a SIMULATOR of prompt-dependent foundation-model errors (synthetic benchmark), not SAM 3: "
             "these teacher numbers describe the simulator."),
    SAM3: TeacherSpec("pipeline.teachers.sam3:Sam3Teacher", "SAM 3 from a local checkpoint folder", ("checkpoint",),
                      note="Teacher = SAM 3 with the six fixed text prompts (backend `sam3`).",
                      check="pipeline.teachers.sam3:check_checkpoint_dir",
                      folder="SAM 3 folder (save_pretrained layout)"),
    IMPORTED: TeacherSpec("pipeline.teachers.imported:ImportedTeacher", "masks made elsewhere (--imported-dir)",
                          ("imported_dir",), use_cache=False, folder="imported teacher masks (see the README layout)"),
}
BACKENDS: tuple[str, ...] = tuple(TEACHER_TABLE)  # the built-in backends (the table holds registered ones too)


def plugin(group: str, name: str, table: dict, kind: type) -> tuple[object, str] | None:
    """Import the plug-in ``name`` of entry-point ``group`` that an installed package declares.

    Parameters
    ----------
    group : str
        :data:`TEACHER_GROUP` or :data:`FORMAT_GROUP`.
    name : str
        The name asked for, absent from ``table``.
    table : dict
        The registry of ``group`` (built-in and registered names).
    kind : type
        What the entry point must be (:class:`TeacherSpec`, ``LabelFormat``).

    Returns
    -------
    tuple of (object, str) or None
        The entry point's object and its distribution as ``"name version"``; None when no package declares
        ``name``.

    Raises
    ------
    InputError
        One line: a plug-in of ``group`` reuses a name the table holds (a built-in's), two packages declare
        ``name``, or its module fails to import or gives no ``kind``.
    """
    points = importlib.metadata.entry_points(group=group)
    for ep in points:  # looked at whenever an unknown name is asked: a clash is refused, never shadowed
        if ep.name in table and _PLUGINS.get((group, ep.name)) != ep.value:
            raise InputError(f"plug-in {ep.name!r} of {_dist(ep)} ({group}) reuses a built-in name: refused")
    found = [ep for ep in points if ep.name == name]
    if len(found) > 1:
        raise InputError(f"plug-in {name!r} ({group}) is declared by {' and '.join(map(_dist, found))}: refused")
    if not found:
        return None
    try:
        obj = found[0].load()
    except Exception as e:  # any failure of a package's own code: one line naming it, not a traceback
        raise InputError(f"plug-in {name!r} of {_dist(found[0])} ({group}): {found[0].value} failed to import: "
                         f"{type(e).__name__}: {e}".splitlines()[0]) from None
    if not isinstance(obj, kind):
        raise InputError(f"plug-in {name!r} of {_dist(found[0])} ({group}): {found[0].value} is no {kind.__name__}")
    _PLUGINS[(group, name)] = found[0].value
    return obj, _dist(found[0])


_PLUGINS: dict[tuple[str, str], str] = {}  # (group, name) -> "module:OBJECT" of the plug-ins loaded


def _dist(ep) -> str:
    return f"{ep.dist.name} {ep.dist.version}" if ep.dist is not None else "an unnamed package"


def find_teacher(name: str) -> TeacherSpec | None:
    """The row of backend ``name``, a plug-in's loaded now (:func:`plugin`); None when there is none."""
    if name not in TEACHER_TABLE and (found := plugin(TEACHER_GROUP, name, TEACHER_TABLE, TeacherSpec)) is not None:
        register_teacher(name, dataclasses.replace(found[0], distribution=found[1]))
    return TEACHER_TABLE.get(name)


def teacher_spec(name: str) -> TeacherSpec:
    """The row of backend ``name`` (a plug-in's loaded now); ValueError naming the backends when there is none (the
    params check names ``teacher.backend``)."""
    if (spec := find_teacher(name)) is None:
        raise ValueError(f"expected one of {', '.join(TEACHER_TABLE)} or an installed plug-in's name ({TEACHER_GROUP})")
    return spec


def is_simulator(name: str) -> bool:
    """Whether backend ``name`` is a SIMULATOR (an unknown name, e.g. an old artifact's, is not)."""
    return (spec := find_teacher(name)) is not None and spec.simulator


def folder_options() -> dict[str, tuple[Option, str]]:
    """Backend -> (its folder option, the option's help) of each row with a ``folder``, in table order: the
    option (``--checkpoint``) sets the row's first setting and implies the backend (label, distill)."""
    return {name: (Option("--" + s.settings[0].replace("_", "-"), s.settings[0]), s.folder)
            for name, s in TEACHER_TABLE.items() if s.folder}


def load(target: str | type):
    """The object ``"module:attribute"`` names (imported now), or ``target`` itself."""
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


def teacher_class(name: str) -> type:
    """The class of backend ``name``."""
    return load(teacher_spec(name).teacher)


def register_teacher(name: str, spec: TeacherSpec) -> None:
    """Add backend ``name`` (``teacher.backend``, ``label --backend`` in a process that registered it first);
    ValueError when the name is taken.  :func:`unregister_teacher` removes it."""
    if name in TEACHER_TABLE:
        raise ValueError(f"teacher backend {name!r} is registered already")
    TEACHER_TABLE[name] = spec


def unregister_teacher(name: str) -> None:
    """Remove a backend :func:`register_teacher` added (a built-in one stays)."""
    if name not in BACKENDS:
        TEACHER_TABLE.pop(name, None)
