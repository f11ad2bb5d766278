"""The teacher backends as data (eq:teacher-prediction), the one registry of their names.

One row per backend with its class, the ``teacher:`` settings it requires and its capabilities.  Pure Python,
so the params schema, the report and ``label --help`` read it without starting torch; :func:`teacher_class`
imports a backend's class (a :class:`pipeline.teachers.base.Teacher`) when it is used.

Plug-ins: an installed package adds a row through the entry-point group :data:`TEACHER_GROUP` (label
formats: :data:`FORMAT_GROUP`), loaded by :func:`plugin` the first time a name is not in the table
(docs/pipeline.md, "How to extend").
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata

from pipeline.runtime.errors import InputError, Option

__all__ = ["SIMULATED", "SAM3", "IMPORTED", "TEACHER_GROUP", "FORMAT_GROUP", "TeacherSpec", "TEACHER_TABLE",
           "BACKENDS", "plugin", "find_teacher", "teacher_spec", "is_simulator", "folder_options", "load",
           "teacher_class", "register_teacher", "unregister_teacher", "TEACHER_ENGINES"]

SIMULATED, SAM3, IMPORTED = "simulated", "sam3", "imported"
#: ``teacher.engine``: how SAM 3's bf16 CPU path runs (pipeline.teachers.attention): torch's ops, the attention in
#: OpenVINO, or each MLP's activation fused into its first linear layer by oneDNN
TEACHER_ENGINES = ("auto", "torch", "openvino", "onednn")
#: the entry-point groups of plug-ins: ``name = "module:OBJECT"``, a :class:`TeacherSpec` / a ``LabelFormat``
TEACHER_GROUP, FORMAT_GROUP = "geodistill.teachers", "geodistill.label_formats"


@dataclasses.dataclass(frozen=True)
class TeacherSpec:
    """One teacher backend: its class, the ``--backend`` help, the settings it requires, its capabilities.

    Attributes
    ----------
    teacher : str or type
        Its class (a :class:`pipeline.teachers.base.Teacher`), or ``"module:Class"``, imported when used.
    description : str
        The ``--backend`` help.
    settings : tuple of str
        The ``teacher.*`` settings it requires (``("checkpoint",)``).
    simulator : bool
        A SIMULATOR of a teacher that reads the reference masks (never a real teacher's labels).
    use_cache : bool
        Its answers go through the teacher cache (False where reading them is as cheap).
    note : str or None
        The report's sentence on its numbers; None: the report names the backend.
    check : str or None
        A ``"module:function"`` called as ``f(value, option)`` on its first setting when a command option
        gives it.
    folder : str or None
        The help of the command option (``--checkpoint``) that sets its first setting, a folder, and implies
        this backend; None: no such option.
    options : str or type or None
        The pydantic model (or ``"module:Model"``) of its ``teacher.options``; None: it takes none.
    distribution : str or None
        A plug-in's ``"name version"``, set when it is loaded (part of the teacher fingerprint: DVC and the
        code version do not see a plug-in's code); None for a built-in.
    """

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
    """Return the ``"name version"`` of the distribution that declares entry point ``ep``."""
    return f"{ep.dist.name} {ep.dist.version}" if ep.dist is not None else "an unnamed package"


def find_teacher(name: str) -> TeacherSpec | None:
    """Find the row of backend ``name``, loading a plug-in's now (:func:`plugin`).

    Parameters
    ----------
    name : str
        A backend name (``teacher.backend``).

    Returns
    -------
    TeacherSpec or None
        Its row; None when neither the table nor an installed plug-in has it.
    """
    if name not in TEACHER_TABLE and (found := plugin(TEACHER_GROUP, name, TEACHER_TABLE, TeacherSpec)) is not None:
        register_teacher(name, dataclasses.replace(found[0], distribution=found[1]))
    return TEACHER_TABLE.get(name)


def teacher_spec(name: str) -> TeacherSpec:
    """Return the row of backend ``name`` (a plug-in's loaded now, :func:`find_teacher`).

    Parameters
    ----------
    name : str
        A backend name (``teacher.backend``).

    Returns
    -------
    TeacherSpec
        Its row.

    Raises
    ------
    ValueError
        No backend has that name; the message names the known ones (the params check adds
        ``teacher.backend``).
    """
    if (spec := find_teacher(name)) is None:
        raise ValueError(f"expected one of {', '.join(TEACHER_TABLE)} or an installed plug-in's name ({TEACHER_GROUP})")
    return spec


def is_simulator(name: str) -> bool:
    """Tell whether backend ``name`` is a SIMULATOR (its row's ``simulator``).

    Parameters
    ----------
    name : str
        A backend name.

    Returns
    -------
    bool
        True for a SIMULATOR; False for a real teacher and for an unknown name (an old artifact's).
    """
    return (spec := find_teacher(name)) is not None and spec.simulator


def folder_options() -> dict[str, tuple[Option, str]]:
    """List the command options that set a backend's folder (label, distill).

    Returns
    -------
    dict of str to tuple of (Option, str)
        Backend -> (its folder option, the option's help), for each row with a ``folder``, in table order: the
        option (``--checkpoint``) sets the row's first setting and implies the backend.
    """
    return {name: (Option("--" + s.settings[0].replace("_", "-"), s.settings[0]), s.folder)
            for name, s in TEACHER_TABLE.items() if s.folder}


def load(target: str | type):
    """Return the object ``"module:attribute"`` names, importing its module now.

    Parameters
    ----------
    target : str or type
        ``"module:attribute"``, or the object itself.

    Returns
    -------
    object
        The attribute of the imported module; ``target`` itself when it is not a string.
    """
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


def teacher_class(name: str) -> type:
    """Return the class of backend ``name``, importing it now.

    Parameters
    ----------
    name : str
        A backend name (:func:`teacher_spec` refuses an unknown one with ValueError).

    Returns
    -------
    type
        Its :class:`pipeline.teachers.base.Teacher` class.
    """
    return load(teacher_spec(name).teacher)


def register_teacher(name: str, spec: TeacherSpec) -> None:
    """Add backend ``name`` to the table, in this process; :func:`unregister_teacher` removes it.

    It is then a ``teacher.backend`` and a ``label --backend`` of this process (an entry point of
    :data:`TEACHER_GROUP` makes it one of every process).

    Parameters
    ----------
    name : str
        The backend's name.
    spec : TeacherSpec
        Its row.

    Raises
    ------
    ValueError
        The name is taken.
    """
    if name in TEACHER_TABLE:
        raise ValueError(f"teacher backend {name!r} is registered already")
    TEACHER_TABLE[name] = spec


def unregister_teacher(name: str) -> None:
    """Remove a backend :func:`register_teacher` added; a built-in one stays.

    Parameters
    ----------
    name : str
        The backend's name (absent: nothing happens).
    """
    if name not in BACKENDS:
        TEACHER_TABLE.pop(name, None)
