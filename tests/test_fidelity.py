"""nvs's network and training step against the authors' code: their three networks, built by their code with its
random initialisation and saved as it saves them, converted by ``nvs.convert``, must give nvs the same depth, every
RGB scale and every loss term for the same images and pose (fp32, CPU).

Runs where ``../shared/reference`` holds the authors' code (CI has it); skipped with the reason otherwise.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import reference_code as rc
from nvs.convert import convert, key_map
from nvs.core.errors import UserError
from nvs.core.geometry import invert_pose
from nvs.run.checkpoints import load_checkpoint, load_weights

pytestmark = pytest.mark.skipif(not rc.available(), reason=f"the authors' code is not at {rc.REFERENCE}")
TOL = 1e-4
S = 256


def _object_pose(elev_a, azim_a, elev_b, azim_b):
    """The authors' ShapeNet pair pose (their RT maps target-camera points into the source camera)."""
    ra = Rotation.from_euler("xyz", [-elev_a, azim_a, 0], degrees=True).as_matrix()
    rb = Rotation.from_euler("xyz", [-elev_b, azim_b, 0], degrees=True).as_matrix()
    R = ra.T @ rb
    c = np.array([0.0, 0.0, 2.0])
    return np.block([[R, (c - R @ c)[:, None]], [np.zeros((1, 3)), 1.0]])


def _scene_pose(rot_deg, t):
    R = Rotation.from_euler("xyz", rot_deg, degrees=True).as_matrix()
    return np.block([[R, np.asarray(t)[:, None]], [np.zeros((1, 3)), 1.0]])


CASES = {
    "chair": dict(data="chairs", f=480.0, pivot=(0.0, 0.0, 2.0),
                  RT=[_object_pose(20, 40, 10, 80), _object_pose(0, 300, 20, 260)]),
    "kitti": dict(data="kitti", f=718.9, pivot=(0.0, 0.0, 0.0),
                  RT=[_scene_pose([0.5, -2.0, 0.3], [0.02, -0.01, 0.12]), _scene_pose([0, 1.0, 0], [-0.03, 0, 0.2])]),
}


def _images(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Source and target batches (2,3,S,S) in [-1,1] (the authors' input range): random smooth images with values
    on a 1/256 grid, so that nvs's [0,1] input maps back to exactly the same [-1,1] values."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(4, 3, 16, 16, generator=g)
    imgs = torch.nn.functional.interpolate(low, size=(S, S), mode="bicubic", align_corners=False).clamp(0, 1)
    imgs = (imgs * 256).round() / 256 * 2 - 1
    return imgs[:2].contiguous(), imgs[2:].contiguous()


@pytest.fixture(scope="module", params=sorted(CASES))
def pair(request, tmp_path_factory):
    """(case, authors' outputs and losses in train and eval mode, nvs module with the converted weights, batch)."""
    case = CASES[request.param]
    tmp = tmp_path_factory.mktemp(f"ref_{request.param}")
    (tmp / "ref").mkdir()
    A, B = _images(1)
    # The same pose in each convention: nvs reads T_tgt_src and inverts it (R^T, -R^T t) where the code reads
    # T_src_tgt; the code is given exactly what nvs computes, so that both project with the same numbers.
    T_tgt_src = invert_pose(torch.tensor(np.stack(case["RT"]), dtype=torch.float32))
    RT = invert_pose(T_tgt_src)
    with rc.imported() as (_, base_model), rc.cuda_is_identity():
        torch.manual_seed(0)
        ref = base_model.BaseModel(rc.options(request.param, str(tmp)))
        ref.set_input({"A": A, "B": B, "RT": RT})
        with rc.losses_only():  # outputs and loss terms are compared, gradients are not
            ref.forward()
            ref.backward_G()
        train = {"depth": ref.depth_tf.detach(), "rgb": [t.detach() for t in (ref.fake_B1, ref.fake_B2, ref.fake_B3,
                                                                               ref.fake_B)],
                 "loss": {"recon": ref.loss_reco.item(), "warp": ref.loss_warp.item(), "vgg": ref.vgg_loss.item(),
                          "edge_smooth": ref.smooth_loss.item(), "depth_consistency": ref.loss_depth.item(),
                          "total": ref.loss_G.item()}}
        ref.switch_mode("eval")
        with torch.no_grad():
            ref.forward()
        evaluation = {"depth": ref.depth_tf, "rgb": [ref.fake_B1, ref.fake_B2, ref.fake_B3, ref.fake_B]}
        ref.switch_mode("train")
        ref.save("latest")
    # fp32 in NCHW, the arithmetic of the code (channels_last picks other conv kernels: ~1e-5 apart)
    ckpt_path = convert([str(tmp / "ref")], data=case["data"], out=str(tmp / "nvs.ckpt"),
                        overrides=("channels_last=false",))
    ckpt = load_checkpoint(str(ckpt_path))
    from omegaconf import OmegaConf

    from nvs.run.build import build_module

    module = build_module(OmegaConf.create(ckpt["nvs_config"]))
    load_weights(module, ckpt, str(ckpt_path))
    K = torch.tensor([[case["f"], 0, 128.0], [0, case["f"], 128.0], [0, 0, 1]]).expand(2, 3, 3).clone()
    batch = {"src": (A + 1) / 2, "tgt": (B + 1) / 2, "K": K, "T_tgt_src": T_tgt_src,
             "pivot": torch.tensor(case["pivot"]).expand(2, 3).clone()}
    module.converted = (ckpt, str(ckpt_path))  # to restore the converted running statistics
    return request.param, train, evaluation, module, batch


def _max_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    assert a.shape == b.shape, (a.shape, b.shape)
    return (a.float() - b.float()).abs().max().item()


def test_train_step_outputs_equal_the_authors(pair):
    name, train, _, module, batch = pair
    module.train()
    out = module.net(batch, module.train_needs)
    diffs = {"depth": _max_diff(out["depth"], train["depth"])}
    diffs.update({f"rgb_{i}": _max_diff(p, r) for i, (p, r) in enumerate(zip(out["rgb_scales"], train["rgb"]))})
    print(name, "train forward max |diff|:", {k: f"{v:.2e}" for k, v in diffs.items()})
    assert max(diffs.values()) <= TOL, diffs


def test_loss_terms_equal_the_authors(pair):
    name, train, _, module, batch = pair
    module.train()
    out = module.net(batch, module.train_needs)
    total, terms = 0.0, {}
    for key, term in module.losses.items():
        terms[key] = term(out, batch).item()
        total += term.weight * terms[key]
    terms["total"] = total
    diffs = {k: abs(terms[k] - v) / max(abs(v), 1e-6) for k, v in train["loss"].items()}
    print(name, "loss terms (nvs, authors', relative diff):",
          {k: (f"{terms[k]:.6f}", f"{train['loss'][k]:.6f}", f"{diffs[k]:.1e}") for k in diffs})
    assert set(terms) == set(train["loss"])
    assert max(diffs.values()) <= TOL, diffs


def test_eval_forward_equals_the_authors(pair):
    name, _, evaluation, module, batch = pair
    load_weights(module, *module.converted)  # the BatchNorm running statistics the code saved (train steps moved them)
    module.eval()
    with torch.no_grad():
        out = module.net(batch)
    diffs = {"depth": _max_diff(out["depth"], evaluation["depth"])}
    diffs.update({f"rgb_{i}": _max_diff(p, r) for i, (p, r) in enumerate(zip(out["rgb_scales"], evaluation["rgb"]))})
    print(name, "eval forward max |diff|:", {k: f"{v:.2e}" for k, v in diffs.items()})
    assert max(diffs.values()) <= TOL, diffs
    module.train()


def test_converter_names_file_and_key(tmp_path):
    with rc.imported() as (networks, _):
        torch.manual_seed(0)
        nets = {"enc": networks.Encoder(3, nz=600), "dec": networks.Decoder(3, nz=600),
                "depthdec": networks.depthDecoder(1, nz=600)}
    for n, net in nets.items():
        torch.save(net.state_dict(), tmp_path / f"7_net_{n}.pth")
    assert set(key_map("depthdec")) == set(nets["depthdec"].state_dict())
    assert set(key_map("dec")) == set(nets["dec"].state_dict())
    assert set(key_map("enc")) == set(nets["enc"].state_dict())
    sd = nets["dec"].state_dict()
    sd.pop("pred2.weight")
    torch.save(sd, tmp_path / "7_net_dec.pth")
    with pytest.raises(UserError, match=r"7_net_dec.pth: missing key 'pred2.weight'"):
        convert([str(tmp_path)])
    sd["pred2.weight"] = torch.zeros(3, 5, 3, 3)
    torch.save(sd, tmp_path / "7_net_dec.pth")
    with pytest.raises(UserError, match=r"7_net_dec.pth: key 'pred2.weight' has shape \(3, 5, 3, 3\)"):
        convert([str(tmp_path)])
    sd = nets["dec"].state_dict()
    sd["extra.weight"] = torch.zeros(1)
    torch.save(sd, tmp_path / "7_net_dec.pth")
    with pytest.raises(UserError, match=r"7_net_dec.pth: unexpected key 'extra.weight'"):
        convert([str(tmp_path)])
    (tmp_path / "7_net_dec.pth").unlink()
    with pytest.raises(UserError, match=r"lacks 7_net_dec.pth"):
        convert([str(tmp_path)])
