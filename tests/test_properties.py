"""Property-based tests: geometry identities, and parsers that never fail with a foreign exception.

The parsers read user files. Whatever the text, they either return a result or raise the project's
own error type (``TrajectoryError`` for trajectories, ``ConfigError`` for reference planes and
configuration): never ``ValueError``, ``IndexError``, ``KeyError``, ``TypeError`` or worse.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kinreg.config import KinregConfig, load_config
from kinreg.errors import ConfigError, TrajectoryError
from kinreg.geometry import Pose, interpolate_poses, quat_to_rotvec, rotvec_to_quat
from kinreg.io.reference_planes import parse_reference_planes, read_reference_planes, reference_planes_from_mapping
from kinreg.io.trajectory import parse_column_mapping, read_trajectory

SETTINGS = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
PARSER_SETTINGS = settings(max_examples=150, deadline=None,
                           suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def outcome(error: type[Exception], fn: Callable[..., Any], *args: Any) -> tuple[Any, Exception | None]:
    """``(result, None)`` or ``(None, the error)``; any other exception propagates (and fails)."""
    try:
        return fn(*args), None
    except error as e:
        return None, e


# --------------------------------------------------------------------------- geometry

translations = arrays(np.float64, (3,), elements=st.floats(-1e3, 1e3, allow_nan=False))
# Rotation vectors of any angle below pi (the log's range), including tiny ones near the
# small-angle branch of rotvec_to_quat / quat_to_rotvec.
directions = arrays(np.float64, (3,), elements=st.floats(-1.0, 1.0, allow_nan=False)).filter(
    lambda v: np.linalg.norm(v) > 1e-3)
angles = st.one_of(st.floats(0.0, math.pi - 1e-3), st.floats(0.0, 1e-6))


@st.composite
def rotvecs(draw: st.DrawFn) -> np.ndarray:
    v = draw(directions)
    return v / np.linalg.norm(v) * draw(angles)


@st.composite
def poses(draw: st.DrawFn) -> Pose:
    return Pose(rotvec_to_quat(draw(rotvecs())), draw(translations))


points = arrays(np.float64, (5, 3), elements=st.floats(-1e3, 1e3, allow_nan=False))


def assert_same_pose(a: Pose, b: Pose, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(a.rotation_matrix, b.rotation_matrix, atol=atol)
    np.testing.assert_allclose(a.t_xyz, b.t_xyz, atol=atol * max(1.0, float(np.abs(b.t_xyz).max())))


@SETTINGS
@given(poses(), poses(), poses())
def test_compose_is_associative(a: Pose, b: Pose, c: Pose) -> None:
    assert_same_pose(a.compose(b).compose(c), a.compose(b.compose(c)))


@SETTINGS
@given(poses(), poses())
def test_inverse_identities(a: Pose, b: Pose) -> None:
    identity = Pose.identity()
    assert_same_pose(a.compose(a.inverse()), identity)
    assert_same_pose(a.inverse().compose(a), identity)
    assert_same_pose(a.inverse().inverse(), a)
    assert_same_pose(a.compose(b).inverse(), b.inverse().compose(a.inverse()))


@SETTINGS
@given(poses(), poses(), points)
def test_apply_follows_compose_and_apply_inverse_undoes_apply(a: Pose, b: Pose, x: np.ndarray) -> None:
    scale = max(1.0, float(np.abs(x).max()), float(np.abs(a.t_xyz).max()), float(np.abs(b.t_xyz).max()))
    np.testing.assert_allclose(a.compose(b).apply(x), a.apply(b.apply(x)), atol=1e-9 * scale)
    np.testing.assert_allclose(a.apply_inverse(a.apply(x)), x, atol=1e-9 * scale)
    np.testing.assert_allclose(a.apply_inverse(x), a.inverse().apply(x), atol=1e-9 * scale)


@SETTINGS
@given(rotvecs(), translations)
def test_log_exp_round_trip(phi: np.ndarray, rho: np.ndarray) -> None:
    xi = np.concatenate([rho, phi])
    pose = Pose.exp(xi)
    np.testing.assert_allclose(np.linalg.norm(pose.quat_wxyz), 1.0, atol=1e-12)
    np.testing.assert_allclose(pose.log(), xi, atol=1e-7 * max(1.0, float(np.abs(rho).max())))
    assert_same_pose(Pose.exp(pose.log()), pose)


@SETTINGS
@given(rotvecs())
def test_quaternion_sign_does_not_change_the_rotation(phi: np.ndarray) -> None:
    q = rotvec_to_quat(phi)
    np.testing.assert_allclose(Pose(-q, np.zeros(3)).rotation_matrix, Pose(q, np.zeros(3)).rotation_matrix,
                               atol=1e-12)
    np.testing.assert_allclose(quat_to_rotvec(-q), phi, atol=1e-9)


@SETTINGS
@given(poses(), rotvecs(), translations, st.floats(0.0, 1.0))
def test_interpolation_is_the_geodesic_between_its_nodes(
    a: Pose, phi: np.ndarray, dt: np.ndarray, u: float
) -> None:
    """Between two poses: position linear, rotation along the shortest arc R_a exp(u log(R_a^T R_b))."""
    step = Pose(rotvec_to_quat(phi), np.zeros(3))
    b = Pose(a.compose(step).quat_wxyz, a.t_xyz + dt)
    nodes = Pose.stack([a, b])
    stamps = np.array([10.0, 12.0])
    got = interpolate_poses(stamps, nodes, np.array([10.0 + 2.0 * u]))[0]
    want_rotation = a.compose(Pose(rotvec_to_quat(u * phi), np.zeros(3))).rotation_matrix
    np.testing.assert_allclose(got.rotation_matrix, want_rotation, atol=1e-8)
    np.testing.assert_allclose(got.t_xyz, a.t_xyz + u * dt, atol=1e-9 * max(1.0, float(np.abs(a.t_xyz).max())))
    # At the nodes the nodes come back; outside the range the end poses are held.
    ends = interpolate_poses(stamps, nodes, np.array([10.0, 12.0, 9.0, 13.0]))
    assert_same_pose(ends[0], a)
    assert_same_pose(ends[1], b)
    assert_same_pose(ends[2], a)
    assert_same_pose(ends[3], b)


# --------------------------------------------------------------------------- trajectory parser

NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**20, 10**20).map(str),
    st.sampled_from(["1623220971.15523", "0", "-0", "1e400", "nan", "inf", "-inf", "0x10", "1_0", "."]),
)
TOKENS = st.one_of(NUMBERS, st.sampled_from(["%time", "#", "# t tx ty tz qx qy qz qw", "x", "q0", "qw", "time",
                                              "ply", "format", "ascii", "binary_little_endian", "element",
                                              "vertex", "property", "double", "list", "end_header", "uchar",
                                              ",", ";", "\t", "\x00", "é"]),
                   st.text(max_size=6))
LINES = st.lists(TOKENS, max_size=10).map(lambda tokens: " ".join(tokens))
CSV_LINES = st.tuples(st.lists(TOKENS, max_size=9), st.sampled_from([",", ";", "\t", " ", ", "])).map(
    lambda td: td[1].join(td[0]))
TEXT_TRAJECTORIES = st.one_of(
    st.text(max_size=400),
    st.lists(CSV_LINES, max_size=8).map("\n".join),
    st.lists(LINES, max_size=12).map("\n".join),
    # Mostly valid rows with one token replaced: reaches the validation after parsing.
    st.lists(st.lists(NUMBERS, min_size=8, max_size=9).map(" ".join), min_size=0, max_size=6).map("\n".join),
)
SUFFIXES = st.sampled_from([".txt", ".tum", ".csv", ".ply", ""])
FORMATS = st.sampled_from([None, "geoslam", "tum", "csv", "ply"])


def _read_trajectory_text(data: bytes, suffix: str, fmt: str | None) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"traj{suffix}"
        path.write_bytes(data)
        traj, error = outcome(TrajectoryError, read_trajectory, path, fmt)
    if error is not None:
        assert str(path) in str(error) and "\n" not in str(error)
        return
    # Whatever was accepted is a valid trajectory.
    assert len(traj) >= 2
    assert np.all(np.diff(traj.stamps_s) > 0)
    assert np.all(np.isfinite(traj.poses.t_xyz))
    np.testing.assert_allclose(np.linalg.norm(traj.poses.quat_wxyz, axis=1), 1.0, atol=1e-12)


@PARSER_SETTINGS
@given(TEXT_TRAJECTORIES, SUFFIXES, FORMATS)
@example(",\n", ".csv", None)  # found by hand: no values at all used to be an IndexError
@example('"abc', ".csv", None)
def test_read_trajectory_on_arbitrary_text_raises_only_trajectory_error(
    text: str, suffix: str, fmt: str | None
) -> None:
    _read_trajectory_text(text.encode("utf-8", errors="surrogatepass"), suffix, fmt)


MAPPINGS = st.lists(st.tuples(st.sampled_from(["time", "x", "y", "z", "qw", "qx", "qy", "qz", "t", "w", ""]),
                               st.sampled_from(["=", "", "=="]),
                               st.one_of(st.sampled_from(["0", "1", "7", "99", "t", "X", ""]), st.text(max_size=3))),
                     max_size=9).map(lambda parts: ",".join("".join(p) for p in parts))


@PARSER_SETTINGS
@given(MAPPINGS, st.lists(CSV_LINES, max_size=6).map("\n".join))
@example("time=0,x=1,y=2,z=3,qw=4,qx=5,qy=6,qz=7", "1,0,0,0,1,0,0,0\n2,0,0,0,1,0,0,0")
@example("time=¹", "")  # a digit that int() does not read
def test_csv_with_any_column_mapping_raises_only_trajectory_error(mapping_text: str, text: str) -> None:
    try:
        mapping = parse_column_mapping(mapping_text)
    except TrajectoryError:
        return
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "traj.csv"
        path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
        with contextlib.suppress(TrajectoryError):
            read_trajectory(path, "csv", mapping)


PLY_HEADERS = st.lists(st.sampled_from([
    "ply", "format ascii 1.0", "format binary_little_endian 1.0", "format binary_big_endian 1.0",
    "format foo 1.0", "element vertex 3", "element vertex -1", "element vertex x", "element face 2",
    "element vertex", "property double time", "property float x", "property double y", "property double z",
    "property double qw", "property double qx", "property double qy", "property double qz", "property",
    "property list uchar int idx", "property quad q", "comment hi", "end_header",
]), max_size=14).map(lambda lines: "\n".join(lines) + "\n")


@PARSER_SETTINGS
@given(PLY_HEADERS, st.binary(max_size=300), st.booleans())
def test_read_trajectory_on_arbitrary_ply_raises_only_trajectory_error(header: str, body: bytes, magic: bool) -> None:
    _read_trajectory_text((("ply\n" if magic else "") + header).encode() + body, ".ply", None)


# --------------------------------------------------------------------------- reference planes

TOML_KEYS = st.sampled_from(["plane_construction_accuracy_m", "name", "axis", "offset_m", "normal_sign", "normal",
                             "d_m", "station", "plane", "reference", "extra", "initial_transform", "rotation_deg",
                             "translation_m", "matrix"])
TOML_VALUES = st.one_of(
    st.sampled_from(['"x"', '"y"', '"z"', '"w"', '""', "1", "-1", "0", "2", "0.05", "-0.05", "nan", "inf", "true",
                     "[0.0, 0.5, 0.866]", "[0, 0, 0]", "[1, 2]", '["a", 1, 2]', "[]", "{}", "1e400", '"wall"',
                     "1979-05-27", "{ a = 1 }", "[[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]",
                     "[[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]", "[[1e308, 0, 0, 0]]"]),
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.text(max_size=5).map(lambda s: '"' + s.replace("\\", "").replace('"', "").replace("\n", "") + '"'),
)
TOML_LINES = st.one_of(
    st.tuples(TOML_KEYS, TOML_VALUES).map(lambda kv: f"{kv[0]} = {kv[1]}"),
    st.sampled_from(["[[plane]]", "[[link]]", "[plane]", "[link]", "[[other]]", "[", "= 1", "# comment", "",
                     "[initial_transform]"]),
)
TOML_DOCUMENTS = st.one_of(st.lists(TOML_LINES, max_size=16).map("\n".join), st.text(max_size=200))


@PARSER_SETTINGS
@given(TOML_DOCUMENTS)
def test_parse_reference_planes_raises_only_config_error(text: str) -> None:
    ref, error = outcome(ConfigError, parse_reference_planes, text, "ref.toml")
    if error is not None:
        assert isinstance(error, ConfigError) and error.path == "ref.toml" and "\n" not in str(error)
        return
    assert ref.accuracy_m > 0 and len(ref.planes) >= 1
    np.testing.assert_allclose(np.linalg.norm(ref.normals, axis=1), 1.0, atol=1e-12)
    assert np.all(np.isfinite(ref.d_m))


@PARSER_SETTINGS
@given(TOML_DOCUMENTS)
def test_read_reference_planes_file_raises_only_config_error(text: str) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "ref.toml"
        path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
        _, error = outcome(ConfigError, read_reference_planes, path)
    assert error is None or (isinstance(error, ConfigError) and error.path == str(path))


toml_like = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=4)),
    lambda children: st.one_of(st.lists(children, max_size=4),
                               st.dictionaries(st.one_of(TOML_KEYS, st.text(max_size=4)), children, max_size=4)),
    max_leaves=12,
)


@PARSER_SETTINGS
@given(st.dictionaries(st.one_of(TOML_KEYS, st.text(max_size=4)), toml_like, max_size=4))
def test_reference_planes_from_any_mapping_raises_only_config_error(doc: dict) -> None:
    with contextlib.suppress(ConfigError):
        reference_planes_from_mapping(doc, source="cfg")


# --------------------------------------------------------------------------- configuration

_DEFAULTS = KinregConfig()
CONFIG_SECTIONS = [name for name in _DEFAULTS.__dataclass_fields__]
CONFIG_KEYS = sorted({k for s in CONFIG_SECTIONS for k in getattr(_DEFAULTS, s).__dataclass_fields__})
CONFIG_LINES = st.one_of(
    st.sampled_from(CONFIG_SECTIONS).map(lambda s: f"[{s}]"),
    st.tuples(st.sampled_from([*CONFIG_KEYS, "schema_version", "bogus"]), TOML_VALUES).map(
        lambda kv: f"{kv[0]} = {kv[1]}"),
    st.sampled_from(['mode = "path"', 'mode = "points"', 'mode = "bogus"', "window_s = -1", "min_points = -5",
                     'temp_dir = 3', "[bogus]", "[slicing.sub]", "slicing = 3", "["]),
)
CONFIG_DOCUMENTS = st.one_of(st.lists(CONFIG_LINES, max_size=12).map("\n".join), st.text(max_size=200),
                             st.binary(max_size=60).map(lambda b: b.decode("latin-1")))


@PARSER_SETTINGS
@given(CONFIG_DOCUMENTS)
def test_load_config_raises_only_config_error(text: str) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "k.toml"
        path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
        cfg, error = outcome(ConfigError, load_config, path)
    if error is not None:
        assert isinstance(error, ConfigError) and error.path == str(path) and "\n" not in str(error)
        return
    assert isinstance(cfg, KinregConfig)
    assert cfg.slicing.window_s > 0


# --------------------------------------------------------------------------- no unsafe loading


def test_no_unsafe_loading_in_kinreg_sources() -> None:
    """Configuration is read with tomllib only; nothing a user supplies is unpickled or evaluated.

    kinreg/run/executor.py may pickle its own arguments to worker processes (multiprocessing does);
    it must not import pickle to load anything."""
    root = Path(__file__).resolve().parents[1]
    sources = [*(root / "kinreg").rglob("*.py"), *(root / "cli").rglob("*.py")]
    assert sources
    forbidden = ("import pickle", "from pickle", "import cPickle", "import dill", "import shelve", "import marshal",
                 "yaml.load(", "yaml.unsafe_load", "allow_pickle=True", "eval(", "exec(")
    offenders = [f"{p.relative_to(root)}: {token}" for p in sources for token in forbidden if token in p.read_text()]
    assert offenders == []
    config_source = (root / "kinreg" / "config.py").read_text()
    assert "tomllib" in config_source and "json.load" not in config_source
