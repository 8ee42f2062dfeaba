"""Chains from URDF files, and calibrated URDF files out.

Only what kinematics needs is read (joints' type, origin, axis, links, mimic and effort
limit; links' inertial mass and centre); meshes and inertia tensors are written back
untouched. Fixed joints fold into the next origin (or the tool), ``continuous`` is revolute,
and a ``mimic`` joint is a coupled passive joint (its offset a turn in its origin).
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

import bayesrob.robot.transforms as tf
from bayesrob.robot.chain import Chain, KinematicsError, Robot, _joint_motion

M_TO_MM = 1000.0


def _floats(text: str | None, n: int, default: list[float], where: str) -> np.ndarray:
    if text is None:
        return np.array(default, float)
    try:
        v = np.array([float(t) for t in text.split()])
    except ValueError:
        raise KinematicsError(f"{where}: expected {n} numbers, got {text!r}") from None
    if v.size != n or not np.all(np.isfinite(v)):
        raise KinematicsError(f"{where}: expected {n} finite numbers, got {text!r}")
    return v


def _parse(path: Path, text: str | None = None) -> ET.Element:
    if text is None and not path.is_file():
        raise KinematicsError(f"{path}: URDF file not found")
    try:
        root = ET.parse(path).getroot() if text is None else ET.fromstring(text)
    except ET.ParseError as exc:
        raise KinematicsError(f"{path}: malformed URDF (XML): {exc}") from None
    if root.tag != "robot":
        raise KinematicsError(f"{path}: not a URDF (root element is <{root.tag}>, not <robot>)")
    _check_references(root, path)
    return root


def _check_references(root: ET.Element, path: Path) -> None:
    """Every name a joint refers to exists, on the chain asked for or not: a misspelt one
    would silently cut a tree or drop a coupling."""
    links = [el.get("name") for el in root.findall("link")]
    joints = [el.get("name") for el in root.findall("joint")]
    for kind, names in (("link", links), ("joint", joints)):
        if None in names:
            raise KinematicsError(f"{path}: a <{kind}> has no name")
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise KinematicsError(f"{path}: {kind} {twice[0]!r} is defined more than once")
    for j in root.findall("joint"):
        for end in ("parent", "child"):
            el = j.find(end)
            if el is None or not el.get("link"):
                raise KinematicsError(f"{path}: joint {j.get('name')!r} has no <{end} link>")
            if el.get("link") not in links:
                raise KinematicsError(f"{path}: joint {j.get('name')!r} names {end} link "
                                      f"{el.get('link')!r}, which is not a link of this URDF")
        mimic = j.find("mimic")
        if mimic is not None and mimic.get("joint") not in joints:
            raise KinematicsError(f"{path}: joint {j.get('name')!r} mimics "
                                  f"{mimic.get('joint')!r}, which is not a joint of this URDF")


def _origin_matrix(joint: ET.Element, where: str) -> np.ndarray:
    o = joint.find("origin")
    xyz = _floats(o.get("xyz") if o is not None else None, 3, [0, 0, 0], f"{where} origin xyz")
    rpy = _floats(o.get("rpy") if o is not None else None, 3, [0, 0, 0], f"{where} origin rpy")
    return tf.np_pose_matrix(np.concatenate([xyz * M_TO_MM, rpy]))


def _inertial(link: ET.Element | None, where: str) -> tuple[float, np.ndarray] | None:
    """A link's mass (kg) and centre of mass (mm, in the link's frame), or None without one."""
    el = link.find("inertial") if link is not None else None
    if el is None:
        return None
    m = el.find("mass")
    try:
        mass = float(m.get("value", "")) if m is not None else float("nan")
    except ValueError:
        mass = float("nan")
    if not (np.isfinite(mass) and mass >= 0):
        raise KinematicsError(f"{where}: <inertial> needs <mass value> a number >= 0 (kg)")
    o = el.find("origin")
    xyz = _floats(o.get("xyz") if o is not None else None, 3, [0, 0, 0], f"{where} inertial "
                  "origin xyz")
    return mass, xyz * M_TO_MM


def _joint_path(root_el: ET.Element, root: str, tip: str, path: Path) -> list[ET.Element]:
    links = {el.get("name") for el in root_el.findall("link")}
    for name, what in ((root, "root"), (tip, "tip")):
        if name not in links:
            raise KinematicsError(f"{path}: {what} link {name!r} is not a link of this URDF")
    by_child = {}
    for j in root_el.findall("joint"):
        child = j.find("child")
        if child is not None:
            by_child[child.get("link")] = j
    chain = []
    link = tip
    while link != root:
        j = by_child.get(link)
        if j is None:
            raise KinematicsError(f"{path}: links {root!r} and {tip!r} are not connected "
                                  f"(no joint leads from {root!r} down to {tip!r})")
        chain.append(j)
        parent = j.find("parent")
        link = parent.get("link") if parent is not None else None
        if link is None:
            raise KinematicsError(f"{path}: joint {j.get('name')!r} has no parent link")
    return chain[::-1]


def urdf_chain(path: str | Path, root: str, tip: str, name: str, *, text: str | None = None,
               **chain_kwargs) -> Chain:
    """The chain of ``path`` from link ``root`` to link ``tip`` (mm, rad). ``text``: the URDF
    itself, read instead of the file (``path`` then only names it in messages)."""
    path = Path(path)
    root_el = _parse(path, text)
    joints = _joint_path(root_el, root, tip, path)
    fixed = np.eye(4)
    prefix: list[str] = []  # fixed joints folded into the next movable joint's origin
    movable, origins, axes, kinds, mimics, prefixes = [], [], [], [], [], []
    efforts: list[float | None] = []  # each joint's <limit effort>, where the file gives it
    links = {el.get("name"): el for el in root_el.findall("link")}
    # per movable joint: its link's mass and first moment (kg, kg mm), the links that fixed
    # joints hang on it folded in; None where its own link gives no <inertial>
    masses: list[float | None] = []
    moments: list[np.ndarray] = []
    unweighed = ""  # why the chain's masses cannot be read: the first link that says so
    for j in joints:
        jname = j.get("name") or "?"
        where = f"{path}: joint {jname!r}"
        jtype = j.get("type")
        t = _origin_matrix(j, where)
        child = j.find("child")
        cname = child.get("link") if child is not None else None
        try:
            inertial = _inertial(links.get(cname), f"{path}: link {cname!r}")
        except KinematicsError as exc:
            # only a fit that holds the masses needs them: it names this, the rest load
            inertial, unweighed = None, unweighed or str(exc)
        if jtype == "fixed":
            fixed = fixed @ t
            prefix.append(jname)
            if inertial is not None and masses and masses[-1] is not None:
                # a link bolted on by fixed joints weighs on the movable joint before them
                masses[-1] += inertial[0]
                moments[-1] = moments[-1] + inertial[0] * (fixed[:3, :3] @ inertial[1]
                                                           + fixed[:3, 3])
            continue
        if jtype not in ("revolute", "continuous", "prismatic"):
            raise KinematicsError(f"{where}: joint type {jtype!r} is not supported "
                                  "(revolute, continuous, prismatic, fixed)")
        ax = j.find("axis")
        axis = _floats(ax.get("xyz") if ax is not None else None, 3, [1, 0, 0], f"{where} axis")
        if np.linalg.norm(axis) < 1e-12:
            raise KinematicsError(f"{where}: axis is zero")
        kind = "prismatic" if jtype == "prismatic" else "revolute"
        mim = j.find("mimic")
        if mim is not None:
            mult = float(mim.get("multiplier", "1"))
            off = float(mim.get("offset", "0")) * (M_TO_MM if kind == "prismatic" else 1.0)
            t = t @ np.asarray(_joint_motion(kind, axis / np.linalg.norm(axis), np.float64(off)))
            mimics.append((mim.get("joint"), mult))
        else:
            mimics.append(None)
        origins.append(tf.matrix_to_pose(fixed @ t))
        prefixes.append(prefix)
        fixed, prefix = np.eye(4), []
        movable.append(jname)
        if inertial is None and not unweighed:
            unweighed = f"{path}: link {cname!r} has no <inertial>"
        masses.append(None if inertial is None else inertial[0])
        moments.append(np.zeros(3) if inertial is None else inertial[0] * inertial[1])
        axes.append(axis)
        kinds.append(kind)
        lim = j.find("limit")
        try:
            effort = float(lim.get("effort", "")) if lim is not None else None
        except ValueError:
            effort = None
        efforts.append(effort if effort is not None and effort > 0 else None)
    if not movable:
        raise KinematicsError(f"{path}: no movable joint between {root!r} and {tip!r}")
    origins.append(tf.matrix_to_pose(fixed))
    actuated = [m for m, mim in zip(movable, mimics, strict=True) if mim is None]
    coupling = np.zeros((len(movable), len(actuated)))
    for i, (m, mim) in enumerate(zip(movable, mimics, strict=True)):
        if mim is None:
            coupling[i, actuated.index(m)] = 1.0
        else:
            if mim[0] not in actuated:
                raise KinematicsError(f"{path}: joint {m!r} mimics {mim[0]!r}, which is not an "
                                      f"actuated joint between {root!r} and {tip!r}")
            coupling[i, actuated.index(mim[0])] = mim[1]
    source = {"kind": "urdf", "path": str(path), **({"text": text} if text is not None else {}),
              "root": root, "tip": tip,
              "efforts": None if None in efforts else efforts,
              # every movable joint's link weighed, or nothing: a chain half described
              # cannot be trusted for its torques
              "link_masses_kg": None if unweighed else masses,
              "link_moments_kg_mm": None if unweighed else [m.tolist() for m in moments],
              "unweighed": unweighed or None,
              "joints": movable, "prefixes": prefixes, "tail": prefix}
    return Chain.build(name, movable, kinds, np.array(axes), np.array(origins),
                       coupling=coupling, source=source, **chain_kwargs)


def _set_origin(joint: ET.Element, t: np.ndarray) -> None:
    pose = tf.matrix_to_pose(t)
    o = joint.find("origin")
    if o is None:
        o = ET.SubElement(joint, "origin")
    o.set("xyz", " ".join(f"{v / M_TO_MM:.12g}" for v in pose[:3]))
    o.set("rpy", " ".join(f"{v:.12g}" for v in pose[3:]))


def _patched(robot: Robot, calibrated: Robot) -> ET.ElementTree:
    """The robot's own URDF with every chain joint's origin replaced by its calibrated one."""
    first = next(iter(robot.chains.values())).source
    tree = (ET.ElementTree(ET.fromstring(first["text"])) if "text" in first
            else ET.parse(first["path"]))
    by_name = {j.get("name"): j for j in tree.getroot().findall("joint")}
    for c in calibrated.chains.values():
        src = c.source
        def product(names: list[str]) -> np.ndarray:
            return functools.reduce(np.matmul, [_origin_matrix(by_name[f], f) for f in names],
                                    np.eye(4))

        for i, jname in enumerate(src["joints"]):
            _set_origin(by_name[jname], np.linalg.inv(product(src["prefixes"][i]))
                        @ tf.np_pose_matrix(c.origins[i]))
        tool = tf.np_pose_matrix(c.origins[-1])
        if src["tail"]:
            _set_origin(by_name[src["tail"][-1]], np.linalg.inv(product(src["tail"][:-1])) @ tool)
        elif not np.allclose(tool, np.eye(4), atol=1e-9):
            raise KinematicsError(
                f"chain {c.name!r}: its tool transform changed but tip link "
                f"{src['tip']!r} has no fixed joint to hold it; calibrate the marker instead")
    return tree


def _generated(calibrated: Robot, name: str) -> ET.ElementTree:
    """A kinematics-only URDF of a robot described by DH tables or planar arms; couplings go
    in the rig file, as ``<mimic>`` follows one joint only, not -(q2 + q3)."""
    robot_el = ET.Element("robot", name=name)
    ET.SubElement(robot_el, "link", name="base_link")

    def joint(name: str, kind: str, parent: str, child: str, origin: np.ndarray) -> ET.Element:
        ET.SubElement(robot_el, "link", name=child)
        j = ET.SubElement(robot_el, "joint", name=name, type=kind)
        ET.SubElement(j, "parent", link=parent)
        ET.SubElement(j, "child", link=child)
        _set_origin(j, tf.np_pose_matrix(origin))
        return j

    for c in calibrated.chains.values():
        parent = f"{c.mount}_tip" if c.mount else "base_link"
        for i, jname in enumerate(c.joint_names):
            j = joint(f"{c.name}_{jname}",
                      "prismatic" if c.kinds[i] == "prismatic" else "continuous", parent,
                      f"{c.name}_link{i + 1}", c.origins[i])
            ET.SubElement(j, "axis", xyz=" ".join(f"{v:.12g}" for v in c.axes[i]))
            parent = f"{c.name}_link{i + 1}"
        joint(f"{c.name}_tool", "fixed", parent, f"{c.name}_tip", c.origins[-1])
    ET.indent(robot_el)
    return ET.ElementTree(robot_el)


def write_urdf(robot: Robot, x: np.ndarray, out: str | Path, name: str = "robot") -> Robot:
    """Write the calibrated robot (parameters x) as URDF and return it: its own file with the
    origins replaced (meshes, inertias and limits survive), else a kinematics-only URDF with
    links ``<arm>_link<i>`` and ``<arm>_tip``; instrument pose and markers go in the rig file."""
    calibrated = robot.with_values(x)
    kinds = {c.source.get("kind") for c in robot.chains.values()}
    files = {c.source.get("path") for c in robot.chains.values()}
    tree = _patched(robot, calibrated) if kinds == {"urdf"} and len(files) == 1 else \
        _generated(calibrated, name)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tree.write(out, encoding="unicode", xml_declaration=True)
    return calibrated


def generated_arm_keys(robot: Robot) -> dict[str, dict]:
    """root/tip of each chain in a URDF written by :func:`write_urdf` from non-URDF chains."""
    out = {}
    for c in robot.chains.values():
        if c.source.get("kind") == "urdf":
            out[c.name] = {"root": c.source["root"], "tip": c.source["tip"]}
        else:
            out[c.name] = {"root": f"{c.mount}_tip" if c.mount else "base_link",
                           "tip": f"{c.name}_tip"}
    return out
