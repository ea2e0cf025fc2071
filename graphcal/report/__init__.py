"""Calibration outputs: calibration.yaml, the calibrated URDF, ROS 2 static transforms, the HTML
report and its figures (docs/outputs.md).

``write_calibration_outputs(result, out_dir)`` writes the five files as one atomic set.
"""

from graphcal.report.calibration_yaml import calibration_to_dict, calibration_yaml_text
from graphcal.report.ros import static_transform_publisher_command, static_transforms_script
from graphcal.report.urdf import calibrated_urdf
from graphcal.report.write import OUTPUT_FILES, write_calibration_outputs


def report_html(result, *, title: str = "graphcal calibration report") -> str:
    """See :func:`graphcal.report.calibration_page.report_html` (imported lazily: it pulls in matplotlib)."""
    from graphcal.report.calibration_page import report_html as _report_html

    return _report_html(result, title=title)


__all__ = [
    "OUTPUT_FILES",
    "calibration_to_dict",
    "calibration_yaml_text",
    "calibrated_urdf",
    "report_html",
    "static_transform_publisher_command",
    "static_transforms_script",
    "write_calibration_outputs",
]
