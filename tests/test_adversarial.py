"""Sun et al.'s adversarial term: a loss that owns its critic, trains it through the module's hook, and checkpoints it."""

import math

import lightning as L
import pytest
import torch
from omegaconf import OmegaConf

from nvs.core.types import RGB_BRANCHES
from nvs.losses.adversarial import AdversarialLoss, PatchDiscriminator
from nvs.run.build import build_module
from tests.conftest import compose_train, fixture_batch


def _module(tmp_path, *overrides, experiment="sun_chairs"):
    cfg = compose_train([f"experiment={experiment}", f"paths.root_dir={tmp_path}", *overrides])
    cfg.paths.output_dir = str(tmp_path)
    OmegaConf.resolve(cfg)
    return build_module(cfg)


def _critic_params(module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.losses["adversarial"].critic.state_dict().items()}


def test_discriminator_is_theirs():
    d = PatchDiscriminator()
    convs = [m for m in d.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [(c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (32, (4, 4), (2, 2)), (64, (4, 4), (2, 2)), (128, (4, 4), (2, 2)), (256, (4, 4), (2, 2)), (1, (1, 1), (1, 1))]
    assert d(torch.zeros(2, 3, 64, 64)).shape == (2, 1, 4, 4)


def test_lsgan_values_by_hand():
    term = AdversarialLoss(branch=None)
    out = {"rgb": torch.full((1, 3, 32, 32), 0.5)}  # 0 on [-1,1]
    batch = {"tgt": torch.ones(1, 3, 32, 32)}
    for m in term.critic.modules():  # a critic that outputs a constant 0.25
        if isinstance(m, torch.nn.Conv2d):
            torch.nn.init.zeros_(m.weight)
            torch.nn.init.zeros_(m.bias)
    torch.nn.init.constant_(term.critic.body[-1].bias, 0.25)
    assert math.isclose(term(out, batch).item(), 0.75 ** 2)
    values = term.critic_loss(out, batch)
    assert math.isclose(values["d_real"].item(), 0.75 ** 2) and math.isclose(values["d_fake"].item(), 0.25 ** 2)


def test_sun_trains_its_critic_by_default_and_the_generator_term_reaches_the_pixel_module(tmp_path):
    module = _module(tmp_path, "model=sun")  # the model's own default loss list
    assert list(module.losses) == ["recon", "branches", "adversarial"]
    module = _module(tmp_path)
    term = module.losses["adversarial"]
    batch = fixture_batch()
    out = module(batch, module.train_needs)
    g = term(out, batch)
    g.backward()
    pixel = [p.grad for p in module.net.pixel_decoder.parameters()]
    assert all(p is not None for p in pixel) and sum(p.abs().sum() for p in pixel) > 0
    # Only the pixel module's prediction is judged: the flow module gets nothing from it, nor does the critic.
    assert all(p.grad is None for p in module.net.flow_decoder.parameters())
    assert all(p.grad is None for p in term.critic.parameters())
    # The network's optimiser does not own the critic.
    opt = module.configure_optimizers()
    owned = {id(p) for group in opt.param_groups for p in group["params"]}
    assert owned == {id(p) for p in module.net.parameters()}
    assert not owned & {id(p) for p in term.critic.parameters()}


def test_the_hook_moves_the_critic_and_a_checkpoint_restores_it(tmp_path):
    module = _module(tmp_path)
    before = _critic_params(module)
    logged = {}
    module.log = lambda name, value, **kw: logged.__setitem__(name, float(value))
    batch = fixture_batch()
    module.training_step(batch, 0)
    after = _critic_params(module)
    assert any(not torch.equal(before[k], after[k]) for k in before)
    assert {"train/adversarial/d_loss", "train/adversarial/d_real", "train/adversarial/d_fake",
            "train/loss/adversarial"} <= set(logged)
    assert int(module.losses["adversarial"].steps) == 1

    # What Lightning writes: the module's state_dict through on_save_checkpoint (frozen loss nets dropped, not this).
    ckpt = {"state_dict": module.state_dict()}
    module.on_save_checkpoint(ckpt)
    keys = [k for k in ckpt["state_dict"] if k.startswith("losses.adversarial.")]
    assert "losses.adversarial.critic.body.0.weight" in keys and "losses.adversarial._extra_state" in keys
    saved_opt = ckpt["state_dict"]["losses.adversarial._extra_state"]["optimizer"]
    assert saved_opt is not None and saved_opt["state"]

    fresh = _module(tmp_path)
    assert any(not torch.equal(after[k], v) for k, v in _critic_params(fresh).items())
    fresh.load_state_dict(ckpt["state_dict"])
    assert all(torch.equal(after[k], v) for k, v in _critic_params(fresh).items())
    term = fresh.losses["adversarial"]
    assert int(term.steps) == 1
    restored = term.optimizer.state_dict()["state"]
    assert torch.equal(restored[0]["exp_avg"], saved_opt["state"][0]["exp_avg"])


def test_frozen_loss_networks_are_still_left_out_of_checkpoints(tmp_path):
    module = _module(tmp_path, "loss=[recon_final,branches,adversarial,vgg]", "loss.vgg.layers=[relu1_2]")
    ckpt = {"state_dict": module.state_dict()}
    module.on_save_checkpoint(ckpt)
    assert not any(k.startswith("losses.vgg.") for k in ckpt["state_dict"])
    assert any(k.startswith("losses.adversarial.") for k in ckpt["state_dict"])


def test_turning_it_off_removes_it(tmp_path):
    module = _module(tmp_path, "loss=[recon_final,branches]")
    assert "adversarial" not in module.losses
    assert not any(k.startswith("losses.") for k in module.state_dict())
    logged = {}
    module.log = lambda name, value, **kw: logged.__setitem__(name, float(value))
    module.training_step(fixture_batch(), 0)
    assert not any("adversarial" in k for k in logged) and "train/loss/branches" in logged


def test_start_step_holds_the_game_back():
    term = AdversarialLoss(branch=None, start_step=2)
    out = {"rgb": torch.rand(1, 3, 32, 32, requires_grad=True)}
    batch = {"tgt": torch.rand(1, 3, 32, 32)}
    before = _params(term.critic)
    assert term.update_critic(out, batch) == {} and term(out, batch).item() == 0.0
    assert term.update_critic(out, batch) == {} and all(torch.equal(before[k], v) for k, v in _params(term.critic).items())
    assert "d_loss" in term.update_critic(out, batch) and term(out, batch).item() > 0


def _params(m):
    return {k: v.detach().clone() for k, v in m.state_dict().items()}


def test_a_training_step_under_bf16_autocast_on_cpu(tmp_path):
    module = _module(tmp_path)
    torch.manual_seed(0)
    logged = {}
    module.log = lambda name, value, **kw: logged.__setitem__(name, float(value))
    before = _critic_params(module)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = module.training_step(fixture_batch(), 0)
    loss.backward()
    assert torch.isfinite(loss) and all(math.isfinite(v) for v in logged.values())
    assert all(v.dtype == torch.float32 for v in _critic_params(module).values())
    assert any(not torch.equal(before[k], v) for k, v in _critic_params(module).items())


@pytest.mark.slow
def test_resume_through_lightning_continues_with_the_saved_critic(tmp_path):
    """A real Trainer: fit 2 steps, save, resume to 3; the resumed critic starts from the saved one."""
    batch = fixture_batch()
    loader = torch.utils.data.DataLoader([batch], batch_size=None)  # one pre-collated batch per epoch
    def trainer(steps):
        return L.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False)

    module = _module(tmp_path)
    t = trainer(2)
    t.fit(module, train_dataloaders=loader)
    path = tmp_path / "a.ckpt"
    t.save_checkpoint(path)
    saved = _critic_params(module)
    resumed = _module(tmp_path)
    seen = {}
    orig = resumed.losses["adversarial"].update_critic

    def spy(out, b):
        seen.setdefault("critic", _critic_params(resumed))
        return orig(out, b)

    resumed.losses["adversarial"].update_critic = spy
    trainer(3).fit(resumed, train_dataloaders=loader, ckpt_path=path)
    assert all(torch.equal(saved[k], v) for k, v in seen["critic"].items())
    assert int(resumed.losses["adversarial"].steps) == 3
