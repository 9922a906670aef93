"""Settings `check-config` once passed that failed only later, found by a bad-input sweep from
config/demo.toml: a missing ONNX model, unknown scenes, a sim camera nowhere, a negative seed,
image sizes no D455 streams, TLS files that are no PEM, a ceiling no scan reads back, names too
long for a file. Each is now a `ConfigError` (exit 78) naming the file and the key before
anything starts, and a good value in its place still loads."""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from silo_agent.base.choices import LAYOUTS, SCENE_LAYOUTS, SCENE_NAMES, SCENE_SITES
from silo_agent.config import ConfigError, SimulationConfig, load_config, parse_config
from silo_agent.reconstruct import site_from_config
from silo_agent.scan import CameraCloud, Scan, ScanError, Site, read_scan, write_scan
from tests.support.cli import run_cli
from tests.support.mqtt_broker import TlsFiles, make_tls

DEMO = Path(__file__).parents[1] / "config" / "demo.toml"
EX_CONFIG = 78  # sysexits.h, written out: not read from the code under test
LONG = "a" * 5000  # a name no file system holds (ENAMETOOLONG)
KEY_PASSWORD = "k3y-pass"


def demo(tmp_path: Path, *edits: tuple[str, str], extra: str = "") -> Path:
    """config/demo.toml with each (old, new) of `edits` made and `extra` appended, its audit
    cache and outbox in `tmp_path`."""
    text = DEMO.read_text(encoding="utf-8")
    for old, new in (
        ('directory = "demo-scans"', f'directory = "{tmp_path / "scans"}"'),
        ('outbox_path = "demo-scans/outbox.sqlite"', f'outbox_path = "{tmp_path / "ob.sqlite"}"'),
        *edits,
    ):
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / "agent.toml"
    path.write_text(text + "\n" + extra + "\n", encoding="utf-8")
    return path


def refused(path: Path, key: str, *fragments: str) -> None:
    """`load_config` refuses `path`, as `run` and `check-config` load it, with one line that
    starts with the file and the key and holds each of `fragments`."""
    with pytest.raises(ConfigError) as caught:
        load_config(path, service=True)
    (line,) = str(caught.value).splitlines()
    assert line.startswith(f"{path}: {key}: "), line
    for fragment in fragments:
        assert fragment in line, line


def tls_section(**keys: object) -> str:
    return "[mqtt.tls]\n" + "".join(f"{k} = {json.dumps(str(v))}\n" for k, v in keys.items())


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> TlsFiles:
    """A throw-away CA and client certificate; the client key encrypted with KEY_PASSWORD."""
    return make_tls(tmp_path_factory.mktemp("pki"), key_password=KEY_PASSWORD)


def plain_key(pki: TlsFiles) -> Path:
    return pki.client_key.with_name("client.key")


def not_pem(tmp_path: Path) -> Path:
    path = tmp_path / "not.pem"
    path.write_text("not a certificate\n")
    return path


# ---------------------------------------------------------------- 1. the ONNX model


def test_a_missing_onnx_model_is_refused_naming_the_key_and_where_it_was_looked_for(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    path = demo(tmp_path, extra='[detection.onnx]\nmodel = "nonexist.onnx"')
    refused(
        path,
        "detection.onnx.model",
        "nonexist.onnx does not exist",
        f"relative path is taken from the working directory, {tmp_path}",
    )
    path = demo(tmp_path, extra=f'[detection.onnx]\nmodel = "{tmp_path}"')
    refused(path, "detection.onnx.model", "is not a regular file")


def test_a_relative_model_path_is_the_one_the_detector_opens_from_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "piles.onnx").write_bytes(b"exists; loaded only by the detector")
    path = demo(tmp_path, extra='[detection.onnx]\nmodel = "models/piles.onnx"')
    monkeypatch.chdir(tmp_path)
    config = load_config(path, service=True)
    assert config.detection.onnx is not None
    assert config.detection.onnx.model == Path("models/piles.onnx")
    monkeypatch.chdir(tmp_path / "models")  # next to the config is not where it is opened
    refused(path, "detection.onnx.model", "does not exist")


def test_a_missing_model_fails_offline_commands_too_not_only_the_service(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    path = demo(tmp_path, extra='[detection.onnx]\nmodel = "nonexist.onnx"')
    with pytest.raises(ConfigError, match=r"detection\.onnx\.model: nonexist\.onnx"):
        load_config(path)


def test_scan_with_a_missing_model_exits_78_before_capturing(tmp_path: Path) -> None:
    path = demo(tmp_path, extra=f'[detection.onnx]\nmodel = "{tmp_path / "nonexist.onnx"}"')
    done = run_cli("scan", "--config", str(path))
    assert done.returncode == EX_CONFIG, done.stderr
    (line,) = done.stderr.splitlines()
    assert f"{path}: detection.onnx.model: " in line and "does not exist" in line
    assert not (tmp_path / "scans").exists()  # nothing captured, nothing written


# ---------------------------------------------------------------- 2. simulation

BAD_SIMULATION = {
    "unknown scene": (
        [('scene = "cone"', 'scene = "cones"')],
        "simulation.scene",
        ["unknown scene 'cones'", "expected one of cone, piles"],
    ),
    "unknown scene in the sequence": (
        [('scene = "cone"', 'scene = "cone"\nsequence = ["flat", "cones"]')],
        "simulation.sequence.1",
        ["unknown scene 'cones'"],
    ),
    "negative seed": (
        [("seed = 0", "seed = -1")],
        "simulation.seed",
        ["greater than or equal to 0"],
    ),
    "sim camera with neither view nor pose": (
        [('view = "A1"', "")],
        "cameras.0",
        ["a sim camera needs view = 'A1'..'A8', extrinsic (4x4) or rotate_deg + translate_m"],
    ),
}


@pytest.mark.parametrize("case", BAD_SIMULATION)
def test_bad_simulation_settings_are_refused(tmp_path: Path, case: str) -> None:
    edits, key, fragments = BAD_SIMULATION[case]
    refused(demo(tmp_path, *edits), key, *fragments)


@pytest.mark.parametrize(
    "edits",
    [
        [('scene = "cone"', 'scene = "bay-cone"')],
        [('scene = "cone"', 'scene = "cone"\nsequence = ["cone", "piles", "ridge"]')],
        [("seed = 0", "seed = 7")],
        [('view = "A1"', "rotate_deg = [0, 0, 0]\ntranslate_m = [0, 0, 2]")],
    ],
)
def test_good_simulation_settings_still_load(tmp_path: Path, edits) -> None:
    load_config(demo(tmp_path, *edits), service=True)


# ---------------------------------------------------------------- 3. image size


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("width", -5, "greater than or equal to 16"),
        ("width", 0, "greater than or equal to 16"),
        ("width", 1_000_000, "less than or equal to 1280"),
        ("height", 721, "less than or equal to 720"),
    ],
)
def test_an_image_size_beyond_the_d455s_is_refused(tmp_path: Path, key, value, expected) -> None:
    path = demo(tmp_path, ('view = "A3"', f'view = "A3"\n{key} = {value}'))
    refused(path, f"cameras.1.{key}", expected)


@pytest.mark.parametrize(("width", "height"), [(1280, 720), (848, 480), (212, 120), (16, 16)])
def test_image_sizes_up_to_the_d455s_largest_still_load(tmp_path: Path, width, height) -> None:
    path = demo(tmp_path, ('view = "A1"', f'view = "A1"\nwidth = {width}\nheight = {height}'))
    camera = load_config(path, service=True).cameras[0]
    assert (camera.width, camera.height) == (width, height)


# ---------------------------------------------------------------- 4. TLS files


def test_a_ca_file_that_is_no_pem_certificate_is_refused(tmp_path: Path, pki: TlsFiles) -> None:
    path = demo(tmp_path, extra=tls_section(ca_file=not_pem(tmp_path)))
    refused(path, "mqtt.tls.ca_file", "not.pem holds no PEM certificate")
    path = demo(tmp_path, extra=tls_section(ca_file=plain_key(pki)))  # a key is no certificate
    refused(path, "mqtt.tls.ca_file", "client.key holds no PEM certificate")


def test_a_client_certificate_or_key_ssl_would_refuse_is_refused(
    tmp_path: Path, pki: TlsFiles
) -> None:
    path = demo(tmp_path, extra=tls_section(cert_file=not_pem(tmp_path), key_file=plain_key(pki)))
    refused(path, "mqtt.tls.cert_file", "not.pem holds no PEM certificate")
    path = demo(tmp_path, extra=tls_section(cert_file=pki.client_cert, key_file=not_pem(tmp_path)))
    refused(path, "mqtt.tls.key_file", "not.pem is not a PEM private key")
    path = demo(tmp_path, extra=tls_section(cert_file=pki.client_cert, key_file=pki.server_key))
    refused(path, "mqtt.tls.key_file", "server.key is not the private key of cert_file")


def test_an_encrypted_key_without_its_passphrase_is_refused_not_asked_for(
    tmp_path: Path, pki: TlsFiles
) -> None:
    keys = {"cert_file": pki.client_cert, "key_file": pki.client_key}
    path = demo(tmp_path, extra=tls_section(**keys))
    refused(path, "mqtt.tls.key_file", "neither key_password_file nor key_password_env")
    wrong = tmp_path / "wrong-pass"
    wrong.write_text("not-it\n")
    path = demo(tmp_path, extra=tls_section(**keys, key_password_file=wrong))
    refused(path, "mqtt.tls.key_file", "passphrase in key_password_file does not decrypt it")


def test_good_tls_files_still_load(
    tmp_path: Path, pki: TlsFiles, monkeypatch: pytest.MonkeyPatch
) -> None:
    plain = {"ca_file": pki.ca, "cert_file": pki.client_cert, "key_file": plain_key(pki)}
    load_config(demo(tmp_path, extra=tls_section(**plain)), service=True)
    password = tmp_path / "key-pass"
    password.write_text(f"{KEY_PASSWORD}\n")  # the first line, as the agent reads it
    encrypted = {"cert_file": pki.client_cert, "key_file": pki.client_key}
    section = tls_section(**encrypted, key_password_file=password)
    load_config(demo(tmp_path, extra=section), service=True)
    monkeypatch.setenv("SILO_TEST_KEY_PASS", KEY_PASSWORD)
    section = tls_section(**encrypted, key_password_env="SILO_TEST_KEY_PASS")
    load_config(demo(tmp_path, extra=section), service=True)


def test_check_config_refuses_a_non_pem_ca_file_with_78_naming_it(tmp_path: Path) -> None:
    path = demo(tmp_path, extra=tls_section(ca_file=not_pem(tmp_path)))
    done = run_cli("check-config", str(path))
    assert done.returncode == EX_CONFIG, done.stderr
    assert done.stderr.splitlines() == [
        f"silo-agent: {path}: mqtt.tls.ca_file: {tmp_path / 'not.pem'} holds no PEM certificate"
    ]


# ---------------------------------------------------------------- 5. floor and ceiling


@pytest.mark.parametrize(
    ("old", "new", "key", "expected"),
    [
        ("ceiling_z = 1.5", "ceiling_z = 150000", "silo.ceiling_z", "less than or equal to 100000"),
        (
            "floor_z = 0.0",
            "floor_z = -150000.0",
            "silo.floor_z",
            "greater than or equal to -100000",
        ),
    ],
)
def test_a_floor_or_ceiling_no_scan_reads_back_is_refused(
    tmp_path: Path, old, new, key, expected
) -> None:
    refused(demo(tmp_path, (old, new)), key, expected)


def _site_config(**silo: object) -> dict:
    region = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
    camera = {"serial": "c", "source": "sim", "view": "A1"}
    return {"silo": {"id": "s", "region": region, **silo}, "cameras": [camera]}


def _write_and_read_back(site: Site, directory: Path) -> None:
    """A one-point scan of `site`, written as the agent writes one and read back."""
    cloud = CameraCloud("c", np.zeros((1, 3), np.float32), np.eye(4))
    read_scan(write_scan(Scan("s-1", "2026-01-01T00:00:00Z", "s", site, [cloud]), directory))


def test_the_config_and_the_scan_reader_share_the_floor_and_ceiling_bound(tmp_path: Path) -> None:
    extremes = parse_config(_site_config(floor_z=-100_000.0, ceiling_z=100_000.0), "bounds")
    _write_and_read_back(site_from_config(extremes), tmp_path / "at")
    for key, value in (("floor_z", -100_000.5), ("ceiling_z", 100_000.5)):
        with pytest.raises(ConfigError, match=f"bounds: silo.{key}: "):
            parse_config(_site_config(**{key: value}), "bounds")
        past = dataclasses.replace(site_from_config(extremes), **{key: value})
        with pytest.raises(ScanError, match=f"site.{key}: "):
            _write_and_read_back(past, tmp_path / key)


# ---------------------------------------------------------------- names too long for a file


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("[silo]", f'[silo]\ntimezone = "{LONG}"', "silo.timezone"),
        ('directory = "demo-scans"', f'directory = "{LONG}"', "audit.directory"),
        (
            'outbox_path = "demo-scans/outbox.sqlite"',
            f'outbox_path = "{LONG}"',
            "mqtt.outbox_path",
        ),
    ],
)
def test_a_name_too_long_for_a_file_is_a_config_error_naming_the_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, old, new, key
) -> None:
    monkeypatch.chdir(tmp_path)  # the relative names are tried here
    text = DEMO.read_text(encoding="utf-8").replace(old, new, 1)
    path = tmp_path / "agent.toml"
    path.write_text(text, encoding="utf-8")
    refused(path, key)


def test_an_outbox_path_naming_the_config_itself_is_refused(tmp_path: Path) -> None:
    """The outbox moves a corrupt database aside and starts afresh (a crash must not stop the
    agent): pointed at the config file itself, `flush` renamed the config and put a database in
    its place. Refused by every command that opens the outbox, the config left as it was."""
    config = tmp_path / "agent.toml"
    demo(tmp_path, (f'outbox_path = "{tmp_path / "ob.sqlite"}"', f'outbox_path = "{config}"'))
    text = config.read_text(encoding="utf-8")
    refused(config, "mqtt.outbox_path", "names this config file itself")
    result = run_cli("flush", "--config", str(config), "--timeout", "0")
    assert result.returncode == EX_CONFIG and "names this config file itself" in result.stderr
    assert config.read_text(encoding="utf-8") == text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["agent.toml"]


# ---------------------------------------------------------------- a layout that fits no camera
# `layout = "eave"` on the cone (no round bin) or "paper" on a scene deeper than 1 m (its cameras
# under the grain) passed `check-config`, then every capture failed.


@pytest.mark.parametrize(
    ("edits", "key", "message"),
    [
        (
            [('layout = "paper"', 'layout = "eave"')],
            "simulation.layout",
            "layout 'eave' does not fit scene 'cone' (it fits paper, wall)",
        ),
        (
            [('scene = "cone"', 'scene = "full"')],
            "simulation.layout",
            "layout 'paper' does not fit scene 'full' (it fits wall)",
        ),
        (
            [('scene = "cone"', 'scene = "cone"\nsequence = ["cone", "piles", "bin-18"]')],
            "simulation.sequence.2",
            "layout 'paper' does not fit scene 'bin-18' (it fits wall, eave)",
        ),
        (
            [
                ('scene = "cone"', 'scene = "bin-heap"\nsequence = ["bin-heap", "ridge"]'),
                ('layout = "paper"', 'layout = "eave"'),
            ],
            "simulation.sequence.1",
            "layout 'eave' does not fit scene 'ridge' (it fits paper, wall)",
        ),
    ],
    ids=["eave on the cone", "paper in full", "paper in a sequence", "eave in a sequence"],
)
def test_a_layout_that_does_not_fit_the_scene_is_refused_naming_the_key(
    tmp_path: Path, edits, key: str, message: str
) -> None:
    path = demo(tmp_path, *edits)
    refused(path, key, message)
    result = run_cli("check-config", str(path))
    assert result.returncode == EX_CONFIG and f"{path}: {key}: {message}" in result.stderr


SITE_SCENES = {
    site: [n for n in SCENE_NAMES if SCENE_SITES[n] == site] for site in SCENE_SITES.values()
}


@pytest.mark.parametrize(
    "edits",
    [
        [('scene = "cone"', 'scene = "hopper-low"')],  # all three fit it
        [('scene = "cone"', 'scene = "bin-18"'), ('layout = "paper"', 'layout = "eave"')],
        # the sequence overrides the scene: the cone, which no eave fits, is not taken
        [
            ('scene = "cone"', 'scene = "cone"\nsequence = ["bin-heap", "bin-crater", "bin-side"]'),
            ('layout = "paper"', 'layout = "eave"'),
        ],
        *(  # a sequence of every scene of a site (a sequence is of one site: SCENE_SITES)
            [
                ('scene = "cone"', f"sequence = {json.dumps(SITE_SCENES[site])}"),
                ('layout = "paper"', 'layout = "wall"'),  # it fits every scene
            ]
            for site in SITE_SCENES
        ),
    ],
)
def test_a_layout_that_fits_every_scene_taken_still_loads(tmp_path: Path, edits) -> None:
    load_config(demo(tmp_path, *edits), service=True)


def test_the_config_takes_exactly_the_layouts_the_table_gives_each_scene() -> None:
    for scene, layout in itertools.product(SCENE_NAMES, LAYOUTS):
        settings = {"scene": scene, "layout": layout}
        if layout in SCENE_LAYOUTS[scene]:
            assert SimulationConfig.model_validate(settings).layout == layout
        else:
            with pytest.raises(ValidationError, match="does not fit"):
                SimulationConfig.model_validate(settings)
