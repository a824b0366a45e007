"""Reference-plane TOML parser: valid files and one clear ConfigError per kind of mistake."""

from __future__ import annotations

import numpy as np
import pytest

from kinreg.errors import ConfigError
from kinreg.io.reference_planes import parse_reference_planes, read_reference_planes

GOOD = """
plane_construction_accuracy_m = 0.05
[[plane]]
name = "south_wall"
axis = "y"
offset_m = 2.0
normal_sign = -1
[[plane]]
name = "slanted_roof"
normal = [0.0, 0.5, 0.866]
d_m = 2.5
[[link]]
station = "qs_00012"
plane = "p3"
reference = "south_wall"
"""


def test_reads_axis_and_general_planes(tmp_path):
    path = tmp_path / "ref.toml"
    path.write_text(GOOD)
    ref = read_reference_planes(path)
    assert ref.accuracy_m == 0.05
    assert ref.names == ("south_wall", "slanted_roof")
    np.testing.assert_allclose(ref.planes[0].normal, [0, -1, 0])
    assert ref.planes[0].d_m == -2.0  # -y . x = -2  <=>  y = 2
    assert np.linalg.norm(ref.planes[1].normal) == pytest.approx(1.0)
    assert ref.planes[1].d_m == 2.5
    assert ref.links[0].reference == "south_wall"
    assert ref.index("slanted_roof") == 1
    assert ref.source == str(path)
    # the same geometric plane: a point at y = 2 lies on it
    assert ref.planes[0].distance_m(np.array([[5.0, 2.0, 1.0]]))[0] == pytest.approx(0.0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\naxis='w'\noffset_m=0\nnormal_sign=1",
         "unknown axis"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\nnormal=[0,0,0]\nd_m=1",
         "normal is zero"),
        ("plane_construction_accuracy_m = -1\n[[plane]]\nname='a'\nnormal=[0,0,1]\nd_m=1", "must be > 0"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\nnormal=[0,0,1]\nd_m=1\n"
         "[[plane]]\nname='a'\nnormal=[0,1,0]\nd_m=1", "duplicate plane name"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\naxis='x'\nnormal_sign=1", "offset_m"),
        ("[[plane]]\nname='a'\nnormal=[0,0,1]\nd_m=1", "plane_construction_accuracy_m"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]\nname='a'", "TOML syntax error"),
        ("plane_construction_accuracy_m = '5cm'\n[[plane]]\nname='a'\nnormal=[0,0,1]\nd_m=1", "number"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\nnormal=[0,1]\nd_m=1", "3 numbers"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\naxis='x'\noffset_m=0\nnormal_sign=2",
         "normal_sign"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\nnormal=[0,0,1]\nd_m=1\naxis='x'",
         "not both"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nnormal=[0,0,1]\nd_m=1", "'name'"),
        ("plane_construction_accuracy_m = 0.05\n[[plane]]\nname='a'\nnormal=[0,0,1]\nd_m=1\n"
         "[[link]]\nstation='s'\nplane='p'\nreference='zz'", "unknown reference plane"),
        ("plane_construction_accuracy_m = 0.05", r"no \[\[plane\]\]"),
    ],
)
def test_errors_are_one_line_config_errors(text, message):
    with pytest.raises(ConfigError, match=message) as info:
        parse_reference_planes(text, source="ref.toml")
    assert "\n" not in str(info.value)
    assert info.value.path == "ref.toml"


def test_missing_file_names_path(tmp_path):
    with pytest.raises(ConfigError, match="not found") as info:
        read_reference_planes(tmp_path / "nope.toml")
    assert info.value.path.endswith("nope.toml")
