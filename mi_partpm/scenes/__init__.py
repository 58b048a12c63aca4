"""Built-in scenes, shipped as Mitsuba XML files and loadable by name.

=====================  ==================================================================
name                   what it is
=====================  ==================================================================
``cornell_box``        the paper's second scene: Cornell box with a mirror and a glass
                       sphere (diffuse and specular surfaces)
``cornell_box_diffuse`` the Cornell box with its two white boxes, diffuse only
``happy_buddha``       the paper's first scene: the Stanford Happy Buddha (20,062 triangles,
                       diffuse) on a floor under an area light; the mesh ships in
                       ``scenes/data/`` (see :mod:`mi_partpm.data`)
=====================  ==================================================================

Every built-in scene takes the parameters ``resx``, ``resy`` (film size, default 480) and
``spp`` (samples per pixel, default 4). ``happy_buddha`` also takes ``mesh`` (the PLY file),
filled in from the package's data (or ``data_dir`` / ``$PARTPM_DATA``) unless given.
"""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Optional, Tuple

import drjit as dr
import numpy as np
import mitsuba as mi

from ..data import find_data_file
from ..props import check_int

log = logging.getLogger("mi_partpm")

__all__ = ["scene_names", "scene_path", "scene_files", "scene_inputs", "load_scene",
           "check_scene", "check_sensor", "scene_bounds", "scene_size", "infinite_sphere",
           "surface_shapes"]

_HERE = Path(__file__).resolve().parent

#: Built-in scene -> {scene parameter: data file it names}.
SCENE_DATA = {"happy_buddha": {"mesh": "happy_buddha_20k.ply"}}


def _resolve(name: str, main: Path, including: Path) -> Optional[Path]:
    """The file ``name`` of a scene as Mitsuba's file resolver finds it: in the main scene
    file's folder (also for a name inside an included file), then in the working folder;
    the including file's own folder last. None where none holds it."""
    for folder in (main.parent, Path.cwd(), including.parent):
        candidate = (folder / name).resolve()
        if candidate.is_file():
            return candidate
    return None


def scene_files(path, errors: Optional[list] = None) -> list:
    """``(file, text, root element)`` of a scene file and of every file it includes
    (``<include filename="..."/>``, found as Mitsuba finds it: :func:`_resolve`), in
    document order, each once; a file that cannot be read or parsed is left out
    (Mitsuba's loader then says what is wrong with it), and added to ``errors`` as
    ``(file, what is wrong)``."""
    import xml.etree.ElementTree as ElementTree
    found, seen = [], set()
    main = Path(path).resolve()

    def visit(file: Path):
        file = file.resolve()
        if file in seen:
            return
        seen.add(file)
        try:
            text = file.read_text(errors="replace")
            root = ElementTree.fromstring(text)
        except (OSError, ValueError, ElementTree.ParseError) as e:
            if errors is not None:
                errors.append((file, getattr(e, "strerror", None) or str(e)))
            return
        found.append((file, text, root))
        for element in root.iter("include"):
            name = element.get("filename")
            named = _resolve(name, main, file) if name else None
            if named is not None:
                visit(named)
    visit(main)
    return found


def scene_inputs(path) -> list:
    """Every file a scene file loads, as far as its text tells: the file, the files it
    includes (:func:`scene_files`), and the existing files its plugins name (``filename``
    values: meshes, bitmaps, spectra), found as Mitsuba finds them (:func:`_resolve`), with
    ``$name`` replaced by the value of a ``<default name="name" .../>``. Sorted, each
    once."""
    files = scene_files(path)
    main = Path(path).resolve()
    defaults = {}
    for _, _, root in files:                     # the first default of a name holds
        for d in root.iter("default"):
            defaults.setdefault(d.get("name"), d.get("value", ""))
    found = {file for file, _, _ in files}
    for file, _, root in files:
        for element in root.iter():
            if element.get("name") != "filename" and not (
                    element.tag == "spectrum" and element.get("filename")):
                continue
            value = re.sub(r"\$(\w+)", lambda m: defaults.get(m.group(1), m.group(0)),
                           element.get("value") or element.get("filename") or "")
            named = _resolve(value, main, file) if value else None
            if named is not None:
                found.add(named)
    return sorted(found)


def scene_names():
    """Names of the built-in scenes."""
    return sorted(p.stem for p in _HERE.glob("*.xml"))


def scene_path(scene: str) -> Path:
    """The XML file of a built-in scene name, or ``scene`` itself if it is a file.

    Raises
    ------
    FileNotFoundError
        Neither a built-in name nor an existing file; the message lists the built-in names.
    """
    builtin = _HERE / f"{scene}.xml"
    if "/" not in scene and "\\" not in scene and builtin.is_file():
        return builtin
    path = Path(scene)
    if path.is_file():
        return path
    raise FileNotFoundError(f"scene {scene!r} is neither a built-in scene "
                            f"({', '.join(scene_names())}) nor an existing file")


def load_scene(scene: str, resolution: Optional[Tuple[int, int]] = None,
               spp: Optional[int] = None, data_dir=None, **params) -> mi.Scene:
    """Load a built-in scene by name, or a scene file by path.

    Parameters
    ----------
    scene : str
        A name from :func:`scene_names` or the path of a Mitsuba XML file.
    resolution : (width, height), optional
        Film size, passed as the scene parameters ``resx`` and ``resy``.
    spp : int, optional
        Samples per pixel, passed as the scene parameter ``spp``.
    data_dir : path, optional
        Directory holding the data files of a built-in scene (default: ``$PARTPM_DATA``, else
        the package's own copies).
    **params
        Further ``$name`` parameters of the scene file.

    Raises
    ------
    FileNotFoundError
        The scene does not exist, or a data file it needs (a mesh) is missing: the message
        says where to get it and where to put it.
    ValueError
        The file does not parse, a parameter is not one the file takes, or ``resolution``
        or ``spp`` is not made of integers >= 1.
    """
    if resolution is not None:
        try:
            if not isinstance(resolution, (tuple, list)) or len(resolution) != 2:
                raise ValueError
            for v in resolution:
                check_int("resolution", v, low=1)
        except ValueError:
            raise ValueError(f"resolution must be (width, height), two integers >= 1, got "
                             f"{resolution!r}") from None
    if spp is not None:
        check_int("spp", spp, low=1)
    path = scene_path(scene)
    if data_dir is not None and not (path.parent == _HERE and path.stem in SCENE_DATA):
        # Once per scene: compare loads its scene more than once.
        _warn_once(("data", str(scene)), "the data folder (--data, data_dir) %s is not used: "
                   "scene %r reads no data file (the scenes that do: %s)", str(data_dir),
                   str(scene), ", ".join(sorted(SCENE_DATA)))
    if path.parent == _HERE:
        for param, name in SCENE_DATA.get(path.stem, {}).items():
            if param not in params:
                params[param] = find_data_file(name, data_dir)
            elif not Path(params[param]).is_file():
                raise FileNotFoundError(f"{param} {str(params[param])!r} of scene "
                                        f"{path.stem!r} is not a file")
    if resolution is not None:
        params["resx"], params["resy"] = int(resolution[0]), int(resolution[1])
    if spp is not None:
        params["spp"] = int(spp)
    # The file and the files it includes: a sensor or a $name may be in either.
    unread = []
    files = scene_files(path, unread)
    text = "".join(t for _, t, _ in files) if files else path.read_text(errors="replace")

    def refuse(message: str):
        # A file that does not parse hides its sensor and its $names: say that instead
        # (a broken tag read as "has no sensor").
        if unread:
            file, what = unread[0]
            fault = "cannot be read" if not Path(file).is_file() or \
                not os.access(file, os.R_OK) else "is not well-formed XML"
            raise ValueError(f"could not load scene {str(path)!r}: {str(file)!r} {fault} "
                             f"({what})")
        raise ValueError(message)
    if ("resx" in params or "spp" in params) and "<sensor" not in text and \
            "<include" not in text:
        refuse(f"scene file {str(path)!r} has no sensor: add a camera to render it")
    for name in params:
        if not re.search(rf"\${re.escape(name)}(?!\w)", text):   # $sp is not $spp's
            option = {"resx": "the resolution (--resolution)", "resy": "the resolution "
                      "(--resolution)", "spp": "the sample count (--spp)"}.get(name)
            if option is None:          # a parameter of the caller's (-D NAME=VALUE)
                refuse(
                    f"scene file {str(path)!r} does not take ${name} (no \"${name}\" in it "
                    f"or the files it includes), so it cannot be set (load_scene's {name}=, "
                    f"render's -D {name}=...)")
            refuse(
                f"scene file {str(path)!r} does not take ${name}, so {option} cannot be set: "
                f"use value=\"${name}\" in it (with <default name=\"{name}\" .../>), or with "
                f"'partpm render' leave the option out (the experiment commands always set it)")
    try:
        return mi.load_file(str(path), **{k: str(v) for k, v in params.items()})
    except RuntimeError as e:
        raise ValueError(f"could not load scene {str(path)!r}: {_loader_message(str(e))}") \
            from None


def _loader_message(text: str) -> str:
    """Mitsuba's message of a scene that did not load, in one line: where in the file, and
    the last line of a plugin's Python traceback (a bad prop of ours) without the traceback
    and without the parser's source location."""
    text = re.sub(r"^\[[\w.]+:\d+\]\s*", "", text.strip())
    head, marker, tail = text.partition("Traceback (most recent call last):")
    if marker and tail.strip():
        # The exception's own lines: from its "...Error: " line on (a message may span
        # lines, e.g. a Transform's value: its last line alone read "]").
        lines = tail.strip().splitlines()
        error = re.compile(r"^(?:\w+\.)*\w*(?:Error|Exception): ")
        first = max((i for i, line in enumerate(lines) if error.match(line)),
                    default=len(lines) - 1)
        text = head.rstrip() + " " + error.sub("", " ".join(lines[first:]))
    return " ".join(text.split())


def _point_text(p) -> str:
    """A point as (x, y, z) of 4 significant digits, for messages (-1.2246e-16 reads 0)."""
    return "(" + ", ".join(f"{0.0 if abs(v) < 1e-9 else v:.4g}" for v in p) + ")"


def scene_bounds(scene: mi.Scene) -> mi.ScalarBoundingBox3f:
    """The bounding box of the scene's shapes. Mitsuba 3.9 merges the meshes of shapes that
    share a BSDF (``<ref id=.../>``, or identical inline ones) into one mesh and leaves that
    mesh's box, and so the scene's, invalid, or holding the first shape's only (a floor
    merged with a cube kept the cube's box); every mesh's box is computed here from its
    vertices (a reduction over its vertex buffer, on the device)."""
    box = mi.ScalarBoundingBox3f()
    for shape in scene.shapes():
        if isinstance(shape, mi.Mesh) and shape.vertex_count():
            shape.recompute_bbox()
        box.expand(shape.bbox())
    return box


def surface_shapes(scene: mi.Scene) -> list:
    """Every shape whose BSDF a ray may meet, as ``(shape, grouped)``: the scene's own
    (``grouped`` False; not its instances, whose surfaces are their groups' shapes) and the
    shapes of its shape groups (True), which ``scene.shapes()`` does not list (found as the
    owners of the scene's parameters: a normal map inside a group went unnoticed and was
    estimated as plain diffuse, 0.73 of path's). A group's shape lies in the group's own
    space, where no ray of the scene meets it."""
    own = [s for s in scene.shapes() if s.class_name() != "Instance"]
    seen = {id(s) for s in scene.shapes()}
    shapes = [(s, False) for s in own]
    params = mi.traverse(scene)
    for key in params.keys():
        owner = params.properties[key][2]
        if isinstance(owner, mi.Shape) and id(owner) not in seen and \
                owner.class_name() != "Instance":
            seen.add(id(owner))
            shapes.append((owner, True))
    return shapes


def scene_size(scene: mi.Scene) -> float:
    """The longest side of :func:`scene_bounds` (0 for a scene without a shape's box)."""
    box = scene_bounds(scene)
    return float(max(box.max[a] - box.min[a] for a in range(3))) if box.valid() else 0.0


def _contains(outer, inner) -> bool:
    """Whether ``outer`` holds ``inner``, up to float rounding (a millionth of its size: a
    rotated wall's vertex at -6e-17 where Mitsuba's box says 0 leaves out nothing)."""
    if not outer.valid():
        return False
    slack = 1e-6 * max(float(outer.max[a] - outer.min[a]) for a in range(3))
    return all(outer.min[a] - slack <= inner.min[a] and inner.max[a] <= outer.max[a] + slack
               for a in range(3))


def _true_box(scene: mi.Scene):
    """The shapes' box where Mitsuba's box of the scene misses some of them, else None."""
    if not scene.shapes():
        return None
    true_box = scene_bounds(scene)
    if not true_box.valid() or _contains(scene.bbox(), true_box):
        return None
    return true_box


def infinite_sphere(scene: mi.Scene):
    """(centre, radius) of the sphere the emitters at infinity emit their photons from: the
    one Mitsuba's ``set_scene`` gives them, around the scene's box (or the shapes' own box,
    after :func:`_repair_infinite_emitters`)."""
    box = _true_box(scene)
    if box is None:
        box = scene.bbox()
    if not box.valid():
        return mi.ScalarPoint3f(0.0), float(mi.math.RayEpsilon)
    sphere = box.bounding_sphere()
    return sphere.center, max(float(mi.math.RayEpsilon),
                              float(sphere.radius) * (1 + float(mi.math.RayEpsilon)))


def _repair_infinite_emitters(scene: mi.Scene, name: Optional[str] = None):
    """Point the emitters at infinity (environment, directional, sun) at the sphere around
    the scene as it is now: Mitsuba's box of the scene, which a parameter update keeps up to
    date but Mitsuba tells these emitters only when it loads the scene. Where that box misses
    shapes (:func:`scene_bounds`) they would emit their photons from the wrong sphere (from
    a point, for an invalid box): they are pointed at the sphere around the shapes' true
    box (at every call: a freed scene's id and box may come back), with a warning once
    per box (a command that checks the scene by name and the render that checks it again
    warn once)."""
    true_box = _true_box(scene)
    infinite = [e for e in scene.emitters()
                if mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)]
    if true_box is None:
        # Mitsuba gives them their sphere when the scene is loaded only: after shapes move
        # (mi.traverse and params.update()) they would emit from the old one (a floor
        # scaled 3x: 0.85 of path under a constant sky). Renewed at every check (cheap).
        for emitter in infinite:
            emitter.set_scene(scene)
        return
    what = "the scene" if name is None else f"scene {name!r}"
    # The repair itself is made every time (it is cheap), the warning once per box.
    _warn_once(("box", str(true_box)), "Mitsuba's bounding box of %s leaves out shapes (it "
               "merged shapes with the same or identical BSDFs into a mesh whose box misses "
               "some of them): "
               "photon mapping uses the box of their vertices, %s to %s%s (nothing for you "
               "to change)",
               what, _point_text(true_box.min), _point_text(true_box.max),
               ", also for the emitters at infinity" if infinite else "", level=logging.INFO)
    if infinite:
        centre, half = true_box.center(), true_box.extents() * 0.5
        stand_in = mi.load_dict({"type": "scene", "box": {
            "type": "cube", "to_world": mi.ScalarTransform4f().translate(centre).scale(
                dr.maximum(half, 1e-6))}})
        for emitter in infinite:
            emitter.set_scene(stand_in)


def linear_part(transform) -> np.ndarray:
    """A transform's matrix without its translation: (3, 3) float64."""
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4)[:3, :3]


def _medium_refusal(what: str, where: str) -> ValueError:
    return ValueError(f"{what} has a participating medium ({where}): photon mapping here "
                      f"renders surfaces only; use Mitsuba's volpath for scenes with media")


#: Instances named in one warning at most (the rest are counted).
_INSTANCES_NAMED = 3


def _check_instances(scene: mi.Scene, instances, what: str):
    """The shapes of a shape group are not among the scene's shapes (only their instances
    are): a medium one of them bounds is found among the scene's parameters instead, and
    refused as on a plain shape. Instances whose to_world shears or scales unevenly get one
    warning per scene: Mitsuba 3.9 gives their surfaces a normal that is not perpendicular
    to them (a sheared cube: n . dp/du = -0.17), which the shading correction and the side
    test read (0.95 of path's mean on a sheared cube's faces; the same matrix as the shapes'
    own to_world gave 1.00). One traversal of the scene and one test of all the matrices
    at once: 3000 instances take about 0.05 s."""
    params = mi.traverse(scene)
    for key in params.keys():
        found = re.match(r"(.+)\.(interior|exterior)_medium\.", key)
        if found:
            raise _medium_refusal(what, f"shape {found.group(1)!r} of a shape group bounds one")
    names = [s.id() for s in instances]
    turns = np.stack([linear_part(params[f"{n}.to_world"] if f"{n}.to_world" in params
                                  else mi.traverse(s)["to_world"])
                      for n, s in zip(names, instances)])
    gram = np.einsum("nki,nkj->nij", turns, turns)
    scale = np.trace(gram, axis1=1, axis2=2) / 3
    uneven = ~np.all(np.abs(gram - scale[:, None, None] * np.eye(3)) <= 1e-4 * 3 *
                     scale[:, None, None], axis=(1, 2))
    if uneven.any():
        bad = [names[k] for k in np.nonzero(uneven)[0]]
        listed = ", ".join(repr(n) for n in bad[:_INSTANCES_NAMED]) + \
            (f" and {len(bad) - _INSTANCES_NAMED} more" if len(bad) > _INSTANCES_NAMED else "")
        _warn_once(("instances", what, tuple(bad)),
                   "%s: %d instance%s (%s) ha%s a to_world that scales unevenly or shears: "
                   "Mitsuba 3.9 gives their surfaces normals that are not perpendicular to "
                   "them, and photon mapping reads those normals, so those surfaces may come "
                   "out a few percent darker than path's; give the shapes that to_world "
                   "themselves instead of the instance", what, len(bad),
                   "" if len(bad) == 1 else "s", listed, "s" if len(bad) == 1 else "ve")


#: The warnings given once per process, by key (what they are about).
_WARNED = set()


def _warn_once(key, message: str, *args, level: int = logging.WARNING):
    """``log.log(level, message, *args)`` the first time ``key`` comes, and never again."""
    if key not in _WARNED:
        _WARNED.add(key)
        log.log(level, message, *args)


def _sensor_name(sensor) -> str:
    return repr(sensor.id()) if sensor.id() else f"(an unnamed {sensor.class_name()})"


def check_sensor(sensor, what: str = "the scene", spp: int = 0):
    """Refuse the sensor a render looks through when a participating medium surrounds it
    (only that one: another sensor of the scene may have one), or its film has no pixel, or
    its sampler takes no sample (``spp``, if not 0, replaces the sampler's count): Mitsuba
    renders neither of the last two (its own integrators end the process with a division by
    zero on a sample count of 0)."""
    if sensor.get_medium() is not None:
        raise _medium_refusal(what, f"around its sensor {_sensor_name(sensor)}")
    size = [int(v) for v in sensor.film().crop_size()]
    if min(size) < 1:
        raise ValueError(f"{what}: the film of sensor {_sensor_name(sensor)} is {size[0]} x {size[1]} "
                         f"pixels; its width and height must be >= 1")
    if spp:                   # (mi.render's spp is unsigned: a nonzero one is >= 1)
        return
    count = int(sensor.sampler().sample_count())
    if count < 1:
        raise ValueError(f"{what}: the sampler of sensor {_sensor_name(sensor)} has "
                         f"sample_count = {count}; give it >= 1 (or render with spp >= 1: "
                         f"mi.render's spp, or --spp for a scene file that takes $spp)")


def check_scene(scene: mi.Scene, name: Optional[str] = None, needs_sensor: bool = True):
    """Refuse a scene photon mapping cannot render: no emitter (nothing would be lit), shapes
    that span less than the photon maps resolve (:data:`~mi_partpm.kdtree.forest.MIN_EXTENT`)
    or, when ``needs_sensor``, no sensor or a first sensor whose film has no pixel or whose
    sampler takes no sample (:func:`check_sensor`). The one check every entry point makes."""
    from ..kdtree.forest import check_span
    what = "the scene" if name is None else f"scene {name!r}"
    _repair_infinite_emitters(scene, name)
    if scene.shapes():
        check_span(scene_size(scene), f"{what} is {{}} across (the longest side of its shapes' "
                   f"bounding box)", "scale the scene up (a to_world scale)")
    if not scene.emitters():
        raise ValueError(f"{what} has no emitter: nothing would be lit (photon mapping needs "
                         f"at least one light)")
    if needs_sensor and not scene.sensors():
        raise ValueError(f"{what} has no sensor: add a camera to render it")
    if needs_sensor:
        check_sensor(scene.sensors()[0], what)
    # Photons and eye paths travel through vacuum only: a medium would be passed through as
    # if it were not there, and the image would be wrong without a word.
    for shape in scene.shapes():
        if shape.is_medium_transition():
            shape_name = repr(shape.id()) if shape.id() else f"a {shape.class_name()}"
            raise _medium_refusal(what, f"shape {shape_name} bounds one")
    instances = [s for s in scene.shapes() if s.class_name() == "Instance"]
    if instances:
        _check_instances(scene, instances, what)
