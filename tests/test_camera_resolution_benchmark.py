"""benchmarks/camera_resolution.py, one real run on the CPU (warp simulation and rendering at both
resolutions, the bundled model in onnxruntime): a 512x512 camera, and a 4:3 one that sees the whole
object, give the estimates of the simulator's own 128x128 masks."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_a_512_camera_gives_the_estimates_of_the_simulators_masks(tmp_path):
    out = tmp_path / "camera.json"
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "camera_resolution.py"), "--instances", "1",
                             "--size", "tiny", "--json", str(out)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    figures = json.loads(out.read_text())
    assert len(figures["setup"]["episodes"]) == 3
    assert figures["against_simulator_masks"]["512x512 camera"] == {"same_family": 1.0, "regl1_between_estimates": 0.0}
    # These objects stay inside the 4:3 view, so letterboxing it gives the square camera's estimates too.
    assert figures["object_pixels_out_of_view"]["512x384 camera (4:3)"] == 0.0
    assert figures["against_simulator_masks"]["512x384 camera (4:3)"]["regl1_between_estimates"] == 0.0
    results = figures["results"]
    simulator = results["128x128 (simulator)"]
    assert simulator == results["512x512 camera"] == results["512x384 camera (4:3)"] and simulator["regl1"] is not None
    # Another framing is another input: the estimates move (by how much is the benchmark's figure).
    assert figures["against_simulator_masks"]["object 0.8x smaller"]["regl1_between_estimates"] > 0
    assert "| 512x384 camera (4:3) | 1.000 | 0.000 |" in result.stdout


def test_a_model_of_grey_masks_gets_the_simulators_grey_masks_as_its_reference(tmp_path):
    """A model of grey masks (ad.mask_levels coverage: here the bundled weights, so marked) reads the
    simulator's coverage masks (generate --coverage-masks) as its 128x128 reference, which a 512x512
    camera's binary mask gives it again through the estimator's coverage resize. Given the binary
    128x128 masks instead, its reference would be masks it was never trained on and the two would differ."""
    import onnx

    from ad_estimator.model import BUNDLED_MODEL

    model = onnx.load(str(BUNDLED_MODEL))
    model.metadata_props.add(key="ad.mask_levels", value="coverage")
    onnx.save(model, str(tmp_path / BUNDLED_MODEL.name))
    encoder = BUNDLED_MODEL.with_name(BUNDLED_MODEL.stem + ".frame.onnx")
    (tmp_path / encoder.name).write_bytes(encoder.read_bytes())
    out = tmp_path / "camera.json"
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "camera_resolution.py"), "--instances", "1",
                             "--size", "tiny", "--model", str(tmp_path / BUNDLED_MODEL.name), "--json", str(out)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    figures = json.loads(out.read_text())
    assert figures["setup"]["mask_levels"] == "coverage"
    assert figures["against_simulator_masks"]["512x512 camera"] == {"same_family": 1.0, "regl1_between_estimates": 0.0}
    results = figures["results"]
    assert results["128x128 (simulator)"] == results["512x512 camera"]
