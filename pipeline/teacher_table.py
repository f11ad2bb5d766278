"""The teacher backends as data (eq:teacher-prediction), the one registry of their names: one row per backend
with its class, the ``teacher:`` settings it requires and its capabilities.  Pure Python, so the params
schema, the report and ``label --help`` read it without starting torch; :func:`teacher_class` imports a
backend's class (a :class:`pipeline.teachers.base.Teacher`) when it is used."""

from __future__ import annotations

import dataclasses
import importlib

SIMULATED, SAM3, IMPORTED = "simulated", "sam3", "imported"


@dataclasses.dataclass(frozen=True)
class TeacherSpec:
    """One backend: its class (``"module:Class"``, imported when used, or the class), the ``--backend`` help,
    the ``teacher.*`` settings it requires, and its capabilities.

    ``simulator``: a SIMULATOR of a teacher that reads the reference masks (never a real teacher's labels);
    ``use_cache``: its answers go through the teacher cache (False where reading them is as cheap);
    ``note``: the report's sentence on its numbers (None: it names the backend); ``check``: a
    ``"module:function"`` called as ``f(value, option)`` on its first setting when a command option gives it."""

    teacher: str | type
    description: str
    settings: tuple[str, ...] = ()
    simulator: bool = False
    use_cache: bool = True
    note: str | None = None
    check: str | None = None


#: name -> backend, in ``--backend``'s order; extend with :func:`register_teacher`
TEACHER_TABLE: dict[str, TeacherSpec] = {
    SIMULATED: TeacherSpec(
        "pipeline.teachers.simulated:SimulatedFoundationTeacher",
        "a SIMULATOR of foundation-model errors (synthetic benchmark; needs --reference-masks)", simulator=True,
        note="Teacher = a SIMULATOR of prompt-dependent foundation-model errors (synthetic benchmark), not SAM 3: "
             "these teacher numbers describe the simulator."),
    SAM3: TeacherSpec("pipeline.teachers.sam3:Sam3Teacher", "SAM 3 from a local checkpoint folder", ("checkpoint",),
                      note="Teacher = SAM 3 with the six fixed text prompts (backend `sam3`).",
                      check="pipeline.teachers.sam3:check_checkpoint_dir"),
    IMPORTED: TeacherSpec("pipeline.teachers.imported:ImportedTeacher", "masks made elsewhere (--imported-dir)",
                          ("imported_dir",), use_cache=False),
}
BACKENDS: tuple[str, ...] = tuple(TEACHER_TABLE)  # the built-in backends (the table holds registered ones too)


def teacher_spec(name: str) -> TeacherSpec:
    """The row of backend ``name``; ValueError naming the backends when there is none."""
    if name not in TEACHER_TABLE:
        raise ValueError(f"teacher.backend={name!r}: expected one of {', '.join(TEACHER_TABLE)}")
    return TEACHER_TABLE[name]


def is_simulator(name: str) -> bool:
    """Whether backend ``name`` is a SIMULATOR (an unknown name, e.g. an old artifact's, is not)."""
    return name in TEACHER_TABLE and TEACHER_TABLE[name].simulator


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
