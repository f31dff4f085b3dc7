"""Numerical stability: geometry round trips and batching (hypothesis), finiteness under extreme inputs, float64
gradcheck through the warp and every loss term, the non-finite loss guard, and the stress report itself."""

import json
import math

import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from kornia.geometry.camera import project_points, unproject_points
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

from nvs import stress
from nvs.core.geometry import inverse_warp, invert_pose, pose_matrix, project_to_source
from nvs.losses.terms import LossTerm
from nvs.module.lightning_module import NonFiniteLossError
import nvs.run.training
from nvs.stress.batches import adversarial_batches, stress_batch
from nvs.stress.geometry import check_warp, geometry_cases
from nvs.stress.gradcheck import float32_inside, float64_kept, gradcheck_cases, run_gradcheck
from nvs.stress.options import train_config
from nvs.stress.precision import forward_backward, warp_position_rows
from nvs.stress.training import train_under_stress
from tests.conftest import compose_train

PROPERTY = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# -- geometry properties --------------------------------------------------------------------------------------------
@st.composite
def cameras(draw, max_size=9):
    """(H, W, K (1,3,3) float64, T (1,4,4) float64, depth (1,1,H,W) float64) with any rotation and a bounded motion."""
    H, W = draw(st.integers(2, max_size)), draw(st.integers(2, max_size))
    f = draw(st.floats(0.5, 1e4))
    cx, cy = draw(st.floats(-2.0, W + 1.0)), draw(st.floats(-2.0, H + 1.0))
    K = torch.tensor([[[f, 0.0, cx], [0.0, f * draw(st.floats(0.5, 2.0)), cy], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    rotvec = draw(st.lists(st.floats(-math.pi, math.pi), min_size=3, max_size=3))
    R = torch.from_numpy(Rotation.from_rotvec(rotvec).as_matrix())[None]
    t = torch.tensor([draw(st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3))], dtype=torch.float64)
    seed = draw(st.integers(0, 2**16))
    scale = draw(st.floats(1e-3, 1e3))
    depth = scale * (0.5 + torch.rand(1, 1, H, W, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    return H, W, K, pose_matrix(R, t), depth


@PROPERTY
@given(cameras())
def test_project_then_unproject_returns_to_the_target_pixel(cam):
    """Target pixel -> source pixel (project_to_source) -> 3D point by kornia's unprojection -> back into the target."""
    H, W, K, T, depth = cam
    uv_src, z_src, in_front = project_to_source(depth, K, T)
    # Only points well in front of the source camera are well conditioned (z_src -> 0 sends uv to infinity).
    ok = in_front & (z_src > 1e-3 * depth[:, 0])
    assume(bool(ok.any()))
    pts_src = unproject_points(uv_src[ok], z_src[ok][:, None], K[0])  # (N,3) in the source camera
    pts_tgt = pts_src @ T[0, :3, :3].T + T[0, :3, 3]
    uv_tgt = project_points(pts_tgt, K[0])
    vs, us = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    grid = torch.stack([us, vs], -1)[None].expand(1, H, W, 2)[ok]
    torch.testing.assert_close(uv_tgt, grid, atol=1e-6 * max(1.0, float(K[0, 0, 0])), rtol=1e-6)
    torch.testing.assert_close(pts_tgt[:, 2], depth[:, 0][ok], atol=0, rtol=1e-9)


@PROPERTY
@given(cameras())
def test_identity_pose_is_identity_warp_for_any_camera(cam):
    H, W, K, _, depth = cam
    src = torch.rand(1, 2, H, W, dtype=torch.float64)
    warped, valid = inverse_warp(src, depth, K, torch.eye(4, dtype=torch.float64)[None])
    assert valid.min() == 1
    torch.testing.assert_close(warped, src, atol=1e-9, rtol=0)


@PROPERTY
@given(st.lists(cameras(max_size=6), min_size=2, max_size=4), st.integers(1, 4))
def test_batched_warp_equals_per_sample(cams, channels):
    H, W = cams[0][0], cams[0][1]
    cams = [c for c in cams if (c[0], c[1]) == (H, W)]
    K = torch.cat([c[2] for c in cams]).float()
    T = torch.cat([c[3] for c in cams]).float()
    depth = torch.cat([c[4] for c in cams]).float()
    src = torch.rand(len(cams), channels, H, W)
    warped, valid = inverse_warp(src, depth, K, T)
    for i in range(len(cams)):
        w_i, v_i = inverse_warp(src[i:i + 1], depth[i:i + 1], K[i:i + 1], T[i:i + 1])
        torch.testing.assert_close(warped[i:i + 1], w_i, atol=1e-6, rtol=0)
        torch.testing.assert_close(valid[i:i + 1], v_i)


@PROPERTY
@given(cameras())
def test_invert_pose_round_trip(cam):
    _, _, _, T, _ = cam
    eye = torch.eye(4, dtype=torch.float64)[None]
    torch.testing.assert_close(invert_pose(T) @ T, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(T @ invert_pose(T), eye, atol=1e-12, rtol=0)


# -- finiteness under extreme inputs --------------------------------------------------------------------------------
CASES = geometry_cases()
OUTSIDE_CONTRACT = {c.name for c in CASES if "outside the contract" in c.name}


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_warp_outputs_and_gradients_stay_finite(case):
    c = check_warp(case)
    assert c.finite_out and c.finite_grad_src_depth and c.masked and c.expectation_met, c
    if case.name not in OUTSIDE_CONTRACT:
        assert c.finite_grad_K_T, c


@pytest.mark.parametrize("case", [c for c in CASES if c.name in OUTSIDE_CONTRACT],
                         ids=[c.name for c in CASES if c.name in OUTSIDE_CONTRACT])
def test_nonfinite_depth_is_no_data(case):
    assert check_warp(case).finite_grad_K_T


def test_geometry_cases_cover_the_issue_ranges():
    names = " ".join(c.name for c in CASES)
    for needle in ("180°", "translation x = 1e-06", "translation x = 1000", "depth 0.0001", "depth 10000",
                   "focal 1 px", "focal 100000 px", "behind", "singular"):
        assert needle in names, needle


# -- float64 gradcheck ----------------------------------------------------------------------------------------------
GRAD_CASES = gradcheck_cases()


def test_gradcheck_covers_every_loss_term():
    """Every loss term class but the adversarial one (its critic trains alongside; tests/test_adversarial.py)."""
    import nvs.losses.branches
    import nvs.losses.terms

    terms = {name for module in (nvs.losses.terms, nvs.losses.branches) for name, obj in vars(module).items()
             if isinstance(obj, type) and issubclass(obj, LossTerm) and obj is not LossTerm}
    covered = {c.name.split(" ")[0] for c in GRAD_CASES}
    assert {"ReconLoss", "VGGLoss", "BranchReconLoss"} <= terms  # the scan finds the classes it should
    assert terms <= covered, terms - covered


@pytest.mark.parametrize("case", GRAD_CASES, ids=[c.name for c in GRAD_CASES])
def test_gradcheck_float64(case):
    """Analytic gradients match finite differences (with float64 kept through ``.float()``)."""
    with float64_kept():
        ok, why = run_gradcheck(case)
    assert ok, why


@pytest.mark.parametrize("case", GRAD_CASES, ids=[c.name for c in GRAD_CASES])
def test_terms_compute_in_float64_as_is(case):
    assert float32_inside(case) == ""


def test_float64_kept_leaves_float64_alone_without_patching_torch():
    x = torch.ones(2, dtype=torch.float64, requires_grad=True)
    original = torch.Tensor.float
    with float64_kept():
        assert torch.Tensor.float is original  # a torch function mode, not a patched class attribute
        kept = x.float()
        assert kept.dtype == torch.float64 and kept is x
        assert torch.ones(2, dtype=torch.bfloat16).float().dtype == torch.float32  # other dtypes still cast
        assert torch.ones(2, dtype=torch.float64).to(torch.float32).dtype == torch.float32  # only .float()
    assert x.float().dtype == torch.float32


def test_float32_inside_names_a_cast_to_float32():
    """The check behind the 'as is' column can fail: a function that drops to float32 inside is named."""
    from nvs.stress.gradcheck import GradcheckCase

    x = torch.rand(3, dtype=torch.float64, requires_grad=True)
    cast_back = GradcheckCase("casts", lambda t: (t.float() * 1.1).to(torch.float64), (x,))
    assert float32_inside(cast_back).startswith("computes in float32 inside")
    returns = GradcheckCase("returns", lambda t: t.float() * 1.1, (x,))
    assert float32_inside(returns) == "returns float32 for float64 inputs"
    assert run_gradcheck(cast_back)[0] is False
    with float64_kept():
        assert run_gradcheck(cast_back) == (True, "")


# -- the stress batches ---------------------------------------------------------------------------------------------
def test_adversarial_batches_follow_the_contract_with_the_stress_camera():
    batches = adversarial_batches(S=16)
    assert len(batches) == 9
    for name, make in batches.items():
        b = make(0)
        assert b["src"].shape == b["tgt"].shape == (2, 3, 16, 16) and b["T_tgt_src"].shape == (2, 4, 4), name
        assert float(b["K"][0, 0, 2]) == 7.5 and torch.equal(b["pivot"][0], torch.tensor([0.0, 0.0, 2.0])), name
    assert float(batches["focal 1 px"](0)["K"][0, 0, 0]) == 1.0
    assert float(batches["focal 1e5 px"](0)["K"][0, 0, 0]) == 1e5
    assert float(batches["constant white images"](0)["src"].min()) == 1.0
    steps = batches["random rotations up to 180°"]
    assert not torch.equal(steps(0)["T_tgt_src"], steps(1)["T_tgt_src"])  # a new rotation every step
    scenes = stress_batch("scenes")
    assert torch.equal(scenes["pivot"], torch.zeros(2, 3)) and float(scenes["K"][0, 0, 0]) == 40.0


# -- precision ------------------------------------------------------------------------------------------------------
def test_paper_model_forward_backward_under_bf16_autocast_is_finite(tmp_path):
    from nvs.run.build import build_module

    module = build_module(train_config(["model=nvs", "loss=[recon,depth_consistency,edge_smooth,warp]"],
                                         str(tmp_path)))
    batch = stress_batch("objects")
    rgb32, d32, _, ok32 = forward_backward(module, batch, None)
    rgb, d, _, ok = forward_backward(module, batch, ("cpu", torch.bfloat16))
    assert ok32 and ok
    assert (rgb - rgb32).abs().mean() < 0.05 and ((d - d32).abs() / d32).mean() < 0.05


def test_warp_under_autocast_samples_where_fp32_does():
    (row,) = warp_position_rows(sizes=(256,))
    projection_max, skip_max = (float(cell.split(" / ")[0]) for cell in row[1:])
    assert projection_max < 0.01 and skip_max < 0.01, row  # pixels


# -- the non-finite loss guard --------------------------------------------------------------------------------------
class NaNFrom(LossTerm):
    """0 x the mean prediction until call ``start``, NaN (connected to the graph) from then on."""

    def __init__(self, start: int, stop: int = 10**9):
        super().__init__(1.0)
        self.start, self.stop, self.calls = start, stop, 0

    def forward(self, out, batch):
        self.calls += 1
        bad = self.start <= self.calls <= self.stop
        return out["rgb"].float().mean() * (float("nan") if bad else 0.0)


def _guard_run(objects_root, tmp_path, monkeypatch, nonfinite: str, nan: NaNFrom):
    cfg = compose_train([f"data.root={objects_root}", f"paths.root_dir={tmp_path}", f"nonfinite={nonfinite}",
                         "trainer.max_steps=4", "trainer.val_check_interval=2", "data.loader.batch_size=2",
                         # Checkpoints are written after each validation (they wait for the monitored val/l1).
                         "loss=[recon]", "test=false", "trainer.enable_progress_bar=false"])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    real = nvs.run.training.build_module

    def with_nan(c, **kwargs):
        module = real(c, **kwargs)
        module.losses["nan"] = nan
        return module

    monkeypatch.setattr(nvs.run.training, "build_module", with_nan)
    return nvs.run.training.run(cfg, tmp_path)


def _finite_checkpoint(path) -> int:
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    assert all(torch.isfinite(v).all() for v in ckpt["state_dict"].values() if v.is_floating_point())
    return int(ckpt["global_step"])


def test_nonfinite_stop_names_the_step_and_keeps_the_last_good_checkpoint(objects_root, tmp_path, monkeypatch):
    with pytest.raises(NonFiniteLossError, match=r"non-finite training loss at step 3 .*last good checkpoint"):
        _guard_run(objects_root, tmp_path, monkeypatch, "stop", NaNFrom(start=4))
    # Steps 0-2 finished, the checkpoint after the validation at step 2 is there and clean; nothing came after.
    assert _finite_checkpoint(tmp_path / "checkpoints" / "last.ckpt") == 2
    assert not (tmp_path / "metrics.json").exists()


def test_nonfinite_skip_drops_the_bad_steps_and_finishes(objects_root, tmp_path, monkeypatch):
    nan = NaNFrom(start=2, stop=3)
    result = _guard_run(objects_root, tmp_path, monkeypatch, "skip", nan)
    assert nan.calls >= 4 and result["steps"] == 4
    # Had the NaN steps been applied, every weight after them would be NaN. (Which validation wrote last.ckpt
    # depends on whether Lightning validates again after the final, step-counting batch: step 2 or 4.)
    assert _finite_checkpoint(tmp_path / "checkpoints" / "last.ckpt") >= 2
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 4


# -- the report -----------------------------------------------------------------------------------------------------
@pytest.mark.slow  # ~35 s: the whole report (make test-all); its parts have fast tests above
def test_stress_report_has_provenance_and_tables(tmp_path):
    out = tmp_path / "stress.md"
    text = stress.main(["--sections", "geometry,gradcheck", "--out", str(out)])
    assert out.read_text() == text
    for needle in ("Command: `python -m nvs.stress --sections geometry,gradcheck", "Git SHA:", "Date:", "Device:",
                   f"torch: {torch.__version__}", "## 1. Geometry under extremes", "## 2. float64 gradcheck",
                   "| identity pose | yes | yes | yes | yes | 1.000 |"):
        assert needle in text, needle
    assert not list(tmp_path.glob(".*.tmp"))


def test_stress_rejects_unknown_sections(tmp_path):
    with pytest.raises(SystemExit):
        stress.main(["--sections", "nope", "--out", str(tmp_path / "x.md")])


def test_training_under_stress_counts_nonfinite_steps():
    """The stress trainer must notice a NaN: a module whose loss is NaN from the second step on."""
    from nvs.models.reference import CopySource
    from nvs.module.lightning_module import NVSModule

    class Tiny(CopySource):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(()))

        def forward(self, batch, needs=frozenset()):
            out = super().forward(batch, needs)
            out["rgb"] = out["rgb"] * self.w
            return out

    module = NVSModule(Tiny(), {"nan": NaNFrom(start=2)}, optimizer=None)
    batch = stress_batch("objects", S=16)
    run = train_under_stress(module, lambda i: batch, steps=3)
    # Anomaly detection stops the NaN backward of step 1 and names it; step 0 was clean.
    assert run.losses == [0.0] and run.error.startswith("step 1:") and "nan" in run.error.lower()


@pytest.mark.slow
def test_determinism_section_runs_the_training_library_call(tmp_path):
    """Three `nvs.run.training.run` runs: the same seed agrees bitwise, the control seed differs."""
    from nvs.stress.determinism import determinism_section

    (same, control) = determinism_section(str(tmp_path))
    n = int(same[1].split("/")[1].split()[0])
    assert same[1] == f"{n}/{n} bitwise equal" and n >= 5
    assert int(control[1].split("/")[0]) > 0
