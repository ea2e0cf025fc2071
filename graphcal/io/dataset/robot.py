"""The robot of a dataset (``robot`` of ``dataset.yaml``) loaded, with a message naming the key
at fault (``robot.urdf``, ``robot.model``, ``robot.base_frame``, ``robot.feet[i]``)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from graphcal.errors import DatasetError, ModelError
from graphcal.io.dataset.model import Dataset, RobotSpec
from graphcal.io.dataset.text import did_you_mean, one_line


def load_robot_spec(root: Path | None, spec: RobotSpec, yaml_file: Path | str):
    """The :class:`~graphcal.models.robot.RobotModel` of ``spec`` (``robot`` of the dataset.yaml
    ``yaml_file``, its URDF relative to the dataset folder ``root``); DatasetError naming the key
    at fault when it cannot be loaded."""
    from graphcal.models.robot import load_robot

    kwargs: dict[str, Any] = {"base_frame": spec.base_frame}
    if spec.urdf is not None:
        if root is None:
            raise DatasetError(yaml_file, "robot.urdf",
                               "a dataset read from a folder (the URDF file is relative to it)")  # fmt: skip
        kwargs["urdf"] = root / spec.urdf.replace("\\", "/")
    else:
        kwargs["model"] = spec.model
    def text(exc: ModelError) -> str:
        msg = str(exc)
        if spec.urdf is not None:
            msg = msg.replace(str(kwargs["urdf"]), spec.urdf)
            if msg.startswith("URDF string"):  # the second load, from the file's text: name the file
                msg = f"URDF file {spec.urdf!r}" + msg[len("URDF string"):]
        return one_line(msg)

    try:
        return load_robot(feet=spec.feet, **kwargs)
    except ModelError as exc:
        first = exc
    # find which key is at fault
    src = "robot.urdf" if spec.urdf is not None else "robot.model"
    src_value = spec.urdf if spec.urdf is not None else spec.model
    try:
        if spec.model is not None:
            from graphcal.models.builtin import BUILTIN_MODELS, builtin_urdf

            if spec.model not in BUILTIN_MODELS:
                raise ModelError(str(first))
            urdf_text = builtin_urdf(spec.model)
        else:
            urdf_text = Path(kwargs["urdf"]).read_text(encoding="utf-8")
        tree = ET.fromstring(urdf_text)
        if tree.tag != "robot":  # not a URDF: load_robot's message says so, not robot.base_frame
            raise ModelError(str(first))
        names = {e.get("name") for e in tree.iter() if e.tag in ("link", "joint")} - {None}
    except (ModelError, OSError, UnicodeDecodeError, ET.ParseError):
        raise DatasetError(yaml_file, src, f"a robot graphcal can load ({text(first)})", src_value) from None
    if spec.base_frame not in names:
        raise DatasetError(yaml_file, "robot.base_frame", "a link or joint of the URDF",
                           f"{spec.base_frame!r}{did_you_mean(spec.base_frame, names)}") from None  # fmt: skip
    for i, foot in enumerate(spec.feet):
        if foot not in names:
            raise DatasetError(yaml_file, f"robot.feet[{i}]", "a link or joint of the URDF",
                               f"{foot!r}{did_you_mean(foot, names)}") from None  # fmt: skip
    try:
        load_robot(urdf_xml=urdf_text, base_frame=spec.base_frame, feet=())
    except ModelError as exc:
        raise DatasetError(yaml_file, src, f"a robot graphcal can load ({text(exc)})", src_value) from None
    raise DatasetError(yaml_file, "robot.feet", f"foot frames below the base frame, on chains of 1-DOF joints "
                       f"({text(first)})", list(spec.feet)) from None  # fmt: skip


def load_dataset_robot(ds: Dataset):
    """The :class:`~graphcal.models.robot.RobotModel` of a dataset (``ds.robot``); DatasetError if it
    cannot be loaded, ValueError if the dataset has no robot."""
    if ds.robot is None:
        raise ValueError("the dataset has no robot")
    yaml_file = ds.root / "dataset.yaml" if ds.root is not None else "dataset.yaml"
    return load_robot_spec(ds.root, ds.robot, yaml_file)
