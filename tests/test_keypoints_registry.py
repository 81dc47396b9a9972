"""Model descriptions, model folders, sha256 checks and `keypoints fetch` against a local HTTP server."""

from __future__ import annotations

import functools
import hashlib
import http.server
import io
import shutil
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from roomcap.core.errors import FormatError
from roomcap.keypoints import registry
from roomcap.keypoints.registry import ModelError, ModelSpec

SHIPPED = [
    "yolox_nano",
    "light_person_detector",
    "blazepose_lite",
    "blazepose_full",
    "blazepose_heavy",
    "movenet_lightning",
    "movenet_lightning_fp16",
    "movenet_thunder",
    "movenet_multipose",
    "openpose_mobilenetv2",
    "hand_landmark_full",
    "hand_landmark_lite",
    "palm_detection_full",
]


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """Empty cache and model folders: nothing but what the test puts there."""
    monkeypatch.setenv("ROOMCAP_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(registry, "shared_models_dir", lambda: tmp_path / "noshared")
    monkeypatch.delenv("ROOMCAP_MODELS", raising=False)
    return tmp_path


def test_builtin_descriptions_cover_shared_and_openmmlab_models():
    specs = registry.list_specs()
    for name in SHIPPED + ["rtmpose_m_halpe26", "rtmpose_s_coco17", "rtmo_m", "yolox_m_humanart"]:
        assert name in specs
    for s in specs.values():
        assert s.role in registry.ROLES
        if s.name not in SHIPPED:
            assert s.urls, f"{s.name} needs a download URL"
    assert specs["rtmpose_m_halpe26"].archive_member == "end2end.onnx"
    sets = registry.model_sets()
    for ms in sets.values():  # every set names described models
        assert ms.pose in specs and (not ms.detector or ms.detector in specs)


def test_shipped_models_resolve_with_matching_sha256(monkeypatch):
    models = need_shared("models")
    monkeypatch.delenv("ROOMCAP_MODELS", raising=False)
    for name in SHIPPED:
        p = registry.resolve(name, models)
        assert p.parent == models
        assert registry.file_sha256(p) == registry.get_spec(name).sha256


def test_unknown_key_and_bad_values_are_rejected_with_the_valid_keys():
    base = {
        "name": "x",
        "role": "detector",
        "file": "x.onnx",
        "input": {"name": "images", "size_wh": [64, 64]},
        "decoder": {"kind": "yolox", "outputs": ["o"]},
    }
    ModelSpec.from_dict(base)
    with pytest.raises(FormatError, match="valid keys"):
        ModelSpec.from_dict({**base, "colour": "RGB"})
    with pytest.raises(FormatError, match="valid keys"):
        ModelSpec.from_dict({**base, "input": {**base["input"], "mean_rgb": [0, 0, 0]}})
    with pytest.raises(FormatError, match="layout"):
        ModelSpec.from_dict({**base, "input": {**base["input"], "layout": "CHW"}})
    with pytest.raises(FormatError, match="role"):
        ModelSpec.from_dict({**base, "role": "pose", "skeleton": "coco17"})  # yolox is a detector decoder
    with pytest.raises(FormatError, match="pixel_coords"):
        ModelSpec.from_dict({**base, "decoder": {**base["decoder"], "pixel_coords": "centre"}})


def test_missing_file_says_which_file_and_where_to_get_it(isolated):
    with pytest.raises(ModelError, match=r"pose_landmark_full\.onnx not found.*ROOMCAP_MODELS"):
        registry.resolve("blazepose_full")
    with pytest.raises(ModelError, match=r"keypoints fetch rtmpose_m_halpe26.*download\.openmmlab\.com"):
        registry.resolve("rtmpose_m_halpe26")


def test_checksum_mismatch_names_the_file(isolated):
    src = need_shared("models", "yolox_nano_416x416.onnx")
    d = isolated / "models"
    d.mkdir()
    data = bytearray(src.read_bytes())
    data[-1] ^= 0xFF
    (d / src.name).write_bytes(bytes(data))
    with pytest.raises(ModelError, match=r"yolox_nano_416x416\.onnx has sha256 .* expects 695e750a"):
        registry.resolve("yolox_nano", d)


def test_user_description_in_model_dir_overrides_and_extends(isolated, monkeypatch):
    d = isolated / "mine"
    d.mkdir()
    text = Path(str(registry.get_spec("yolox_nano").source)).read_text()
    (d / "my_det.toml").write_text(text.replace('name = "yolox_nano"', 'name = "my_det"'))
    monkeypatch.setenv("ROOMCAP_MODELS", str(d))
    assert registry.get_spec("my_det").file == "yolox_nano_416x416.onnx"
    assert registry.get_model_set("my_det+blazepose_full").detector == "my_det"


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *a):
        pass


@pytest.fixture
def server(tmp_path):
    root = tmp_path / "www"
    root.mkdir()
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(root)))
    th = threading.Thread(target=httpd.serve_forever, daemon=True)
    th.start()
    yield root, f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


def _spec_for(name, file, url, sha="", member="", mirrors=()):
    return ModelSpec.from_dict(
        {
            "name": name,
            "role": "detector",
            "file": file,
            "sha256": sha,
            "url": url,
            "archive_member": member,
            "mirrors": list(mirrors),
            "input": {"name": "images", "size_wh": [416, 416]},
            "decoder": {"kind": "yolox", "outputs": ["output"]},
        }
    )


def test_fetch_from_local_server_checks_sha256(isolated, server):
    root, base = server
    src = need_shared("models", "light_person_detector_192x192.onnx")
    shutil.copy(src, root / src.name)
    good = registry.get_spec("light_person_detector").sha256
    spec = _spec_for("lp", src.name, f"{base}/{src.name}", sha=good)
    p = registry.fetch(spec)
    assert p.parent == isolated / "cache" and registry.sha256_file(p) == good
    p.unlink()
    bad = _spec_for("lp", src.name, f"{base}/{src.name}", sha="0" * 64)
    with pytest.raises(ModelError, match="sha256"):
        registry.fetch(bad)
    assert not p.exists()  # a bad download is never left in the cache
    # first URL broken, the mirror works
    spec2 = _spec_for("lp", src.name, f"{base}/missing.onnx", sha=good, mirrors=[f"{base}/{src.name}"])
    assert registry.sha256_file(registry.fetch(spec2)) == good


def test_fetch_unpacks_openmmlab_zip_and_records_sha(isolated, server):
    root, base = server
    src = need_shared("models", "light_person_detector_192x192.onnx")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("rtm-sdk/deploy.json", "{}")
        z.write(src, "rtm-sdk/end2end.onnx")
    (root / "model.zip").write_bytes(buf.getvalue())
    spec = _spec_for("z", "z.onnx", f"{base}/model.zip", member="end2end.onnx")  # no sha256 known
    p = registry.fetch(spec)
    want = hashlib.sha256(src.read_bytes()).hexdigest()
    assert registry.sha256_file(p) == want
    lock = registry.load_toml(registry.lock_file(p.parent))  # trust on first use, in the lock file
    assert lock["models"]["z"] == {"file": "z.onnx", "sha256": want, "url": f"{base}/model.zip"}
    data = bytearray(p.read_bytes())
    data[10] ^= 1
    p.write_bytes(bytes(data))  # later damage is caught against the recorded digest
    with pytest.raises(ModelError, match="z.onnx has sha256"):
        registry.resolve(spec)


def test_cli_list_and_fetch(isolated, server, capsys):
    from roomcap.keypoints.cli import main

    root, base = server
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "blazepose_full" in out and "model sets" in out
    src = need_shared("models", "movenet_singlepose_lightning_int8.onnx")
    shutil.copy(src, root / src.name)
    d = isolated / "models"
    d.mkdir()
    text = Path(str(registry.get_spec("movenet_lightning").source)).read_text()
    (d / "mv.toml").write_text(
        text.replace('name = "movenet_lightning"', 'name = "mv"').replace(
            'url = ""', f'url = "{base}/{src.name}"'
        )
    )
    assert main(["--model-dir", str(d), "fetch", "mv"]) == 0
    assert (d / src.name).exists()
    assert main(["fetch", "no_such_model"]) == 2
    assert np.isfinite(1.0)
