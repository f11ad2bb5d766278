"""The notebook API: ``pipeline.label``, ``pipeline.distill`` and ``pipeline.Segmenter.from_bundle(path).predict``
(any size, grey / RGB / RGBA, 8-bit / 16-bit / float, path or array -> a bool mask at the original size);
and ``geodistill --version``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

import pipeline
from tests.builders.teacher import checkpoint_folder, make_image_folder


@pytest.fixture(scope="module")
def student(tmp_path_factory):
    """A checkpoint directory (model.pt of a small random TinyUNet, tau 0.5, trained at 32 px)."""
    import torch

    from pipeline.model import TinyUNet

    torch.manual_seed(0)
    model = TinyUNet(channels=(4, 8, 8)).eval()
    path = tmp_path_factory.mktemp("student")
    torch.save({"state_dict": model.mask_path_state_dict(), "config": dict(model.config), "tau": 0.5,
                "resolution": 32, "method": "plain", "seed": 0}, path / "model.pt")
    return path


@pytest.fixture(scope="module")
def seg(student):
    return pipeline.Segmenter.from_bundle(student)


def _scene(h: int, w: int) -> np.ndarray:
    rng = np.random.default_rng(h * 1000 + w)
    img = rng.integers(0, 60, (h, w, 3)).astype(np.uint8)
    cv2.circle(img, (w // 2, h // 3), min(h, w) // 4, (230, 200, 90), -1)
    return img


def test_segmenter_from_bundle_resolves_tau_and_resolution(seg):
    assert seg.tau == 0.5 and seg.tau_source == "checkpoint payload" and seg.resolution == 32


@pytest.mark.parametrize("h, w", [(45, 77), (128, 96), (17, 23)])
def test_predict_any_dtype_and_channels_at_the_original_size(seg, h, w):
    import dataclasses

    rgb = _scene(h, w)
    probs = seg.probabilities(rgb)
    assert probs.shape == (h, w) and 0 < probs.min() < probs.max() < 1
    seg = dataclasses.replace(seg, tau=float(np.median(probs)))  # a random student: split the picture in two
    ref = seg.predict(rgb)
    assert ref.shape == (h, w) and ref.dtype == bool and 0.3 < ref.mean() < 0.7
    assert np.array_equal(ref, probs >= seg.tau)
    # the same picture in other encodings gives the same mask
    rgba = np.dstack([rgb, np.full((h, w), 7, np.uint8)])                       # alpha dropped
    assert np.array_equal(seg.predict(rgba), ref)
    assert np.array_equal(seg.predict(rgb.astype(np.uint16) * 257), ref)         # 16-bit
    assert np.array_equal(seg.predict(rgb.astype(np.float32) / 255), ref)        # float in [0, 1]
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    grey_mask = seg.predict(grey)
    assert grey_mask.shape == (h, w)
    assert np.array_equal(seg.predict(grey[..., None]), grey_mask)              # [H, W, 1]
    assert np.array_equal(seg.predict(grey.astype(np.uint16) * 257), grey_mask)  # 16-bit grey
    assert np.array_equal(seg.predict(np.repeat(grey[..., None], 3, axis=2)), grey_mask)  # grey = replicated


def test_predict_a_path_equals_the_array(seg, tmp_path):
    import dataclasses

    rgb = _scene(50, 70)
    f16 = tmp_path / "x16.png"
    cv2.imwrite(str(f16), rgb[..., ::-1].astype(np.uint16) * 257)   # 16-bit RGB file (OpenCV writes BGR)
    fa = tmp_path / "xa.png"
    cv2.imwrite(str(fa), np.dstack([rgb[..., ::-1], np.full((50, 70), 255, np.uint8)]))  # RGBA file
    seg = dataclasses.replace(seg, tau=float(np.median(seg.probabilities(rgb))))
    ref = seg.predict(rgb)
    assert 0.3 < ref.mean() < 0.7
    assert np.array_equal(seg.predict(f16), ref) and np.array_equal(seg.predict(str(fa)), ref)
    assert not np.array_equal(seg.predict(rgb[..., ::-1]), ref)  # channel order matters: RGB is RGB


def test_segmenter_errors_are_input_errors(seg, tmp_path):
    from pipeline.runtime.errors import InputError

    with pytest.raises(InputError, match="not found"):
        pipeline.Segmenter.from_bundle(tmp_path / "nope")
    with pytest.raises(InputError, match="unsupported image shape|unsupported channel"):
        seg.predict(np.zeros((4, 4, 2, 2), np.uint8))


def test_label_and_distill_are_exported(tmp_path):
    """pipeline.label runs the folder labelling (simulated backend: a SIMULATOR reading the masks);
    pipeline.distill(run=False) writes the DVC project with the overrides and the teacher."""
    import yaml

    images, masks = make_image_folder(tmp_path / "data", n=6)
    res = pipeline.label(images, out=tmp_path / "labels", backend="simulated", reference_masks=masks,
                         formats="png", overrides={"data.resolution": 32}, device="cpu")
    assert res.simulator and len(res.table) == 6 and res.formats == ("png",)
    assert len(list((tmp_path / "labels" / "masks").glob("*.png"))) == 6
    sam3 = checkpoint_folder(tmp_path / "sam3")  # the project is written, not run
    out = pipeline.distill(images, out=tmp_path / "proj", checkpoint=sam3, overrides=["train.epochs_stage1=2"],
                           run=False)
    params = yaml.safe_load((tmp_path / "proj" / "params.yaml").read_text())
    assert params["train"]["epochs_stage1"] == 2 and params["teacher"]["checkpoint"] == str(sam3.resolve())
    assert params["profile"] == "distill" and params["data"]["root"] == str(images.resolve())
    assert out["deploy"] == (tmp_path / "proj" / "artifacts" / "deploy").resolve()
    assert (tmp_path / "proj" / ".dvc").is_dir() and (tmp_path / "proj" / "dvc.yaml").is_file()


def test_version_option():
    from pipeline.cli.main import main

    res = CliRunner().invoke(main, ["--version"])
    assert res.exit_code == 0 and res.output.strip() == f"geodistill {pipeline.__version__}"
    # one version, written once: the installed distribution reads it from pipeline.__version__
    import importlib.metadata

    assert importlib.metadata.version("geodistill-refine") == pipeline.__version__


def test_distill_project_has_the_plot_template_its_dvc_yaml_names(tmp_path):
    """dvc.yaml's plots name .dvc/plots/<template>.json: a distill project without it fails `dvc plots show`."""
    import yaml

    from pipeline.report.offline_plots import template_path, template_text

    images, masks = make_image_folder(tmp_path / "data", n=4)
    sam3 = checkpoint_folder(tmp_path / "sam3")
    pipeline.distill(images, out=tmp_path / "proj", val_masks=masks, checkpoint=sam3, run=False)
    doc = yaml.safe_load((tmp_path / "proj" / "dvc.yaml").read_text())
    names = {v["template"] for p in doc["plots"] for v in p.values()}
    assert {template_path(tmp_path / "proj").stem} == names
    assert template_path(tmp_path / "proj").read_text() == template_text()
    assert (tmp_path / "proj" / ".dvc" / "config").is_file()  # still initialised as a DVC project
