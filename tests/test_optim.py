"""OneLaunchAdam (train/optim.py) against torch.optim.Adam: same parameters up to float rounding, the
same moments and step counts exactly, skipped steps (found_inf) change nothing, checkpoints interchange."""

import io

import pytest
import torch

from devices import DEVICES
from rmavatar.bench.counting import OpCounter
from rmavatar.train.optim import OneLaunchAdam

SHAPES = [(40, 3), (40, 4), (40, 1), (2, 15, 3), (7,)]
LRS = [0.008, 0.001, 0.05, 0.0025 / 20, 1e-4]


def _setup(device, cls, **kw):
    gen = torch.Generator().manual_seed(0)
    params = [torch.nn.Parameter(torch.randn(s, generator=gen).to(device)) for s in SHAPES]
    groups = [{"name": f"g{i}", "params": [p], "lr": lr} for i, (p, lr) in enumerate(zip(params, LRS))]
    return params, cls(groups, eps=1e-15, **kw)


def _grads(step, device):
    gen = torch.Generator().manual_seed(100 + step)
    return [torch.randn(s, generator=gen).to(device) for s in SHAPES]


def _step(params, opt, grads, found_inf=None, lr0=None):
    for p, g in zip(params, grads):
        p.grad = g.clone()
    if lr0 is not None:
        opt.param_groups[0]["lr"] = lr0
    opt.found_inf = found_inf
    opt.step()


def _assert_close(ref_params, ref_opt, params, opt):
    """Parameters to float32 rounding (relative to the value, or to the lr near zero); moments and
    step counts bit-equal (the same fused kernel computes them from the same gradients)."""
    for p_ref, p, lr in zip(ref_params, params, LRS):
        torch.testing.assert_close(p, p_ref, rtol=1e-6, atol=1e-6 * lr)
        s_ref, s = ref_opt.state[p_ref], opt.state[p]
        assert set(s) == set(s_ref) == {"step", "exp_avg", "exp_avg_sq"}
        for key in s:
            assert torch.equal(s[key], s_ref[key]), key


@pytest.mark.parametrize("device", DEVICES)
def test_matches_torch_adam_with_skips_and_lr_changes(device):
    ref_params, ref = _setup(device, torch.optim.Adam, fused=True)
    params, opt = _setup(device, OneLaunchAdam)
    zero, one = torch.zeros((), device=device), torch.ones((), device=device)
    for k in range(10):
        grads = _grads(k, device)
        skip = one if k in (0, 4, 5) else zero  # the very first step too: state exists, nothing moves
        lr0 = 0.004 if k == 6 else (0.002 if k == 8 else None)
        before = [p.detach().clone() for p in params]
        moments = [{key: v.clone() for key, v in opt.state[p].items()} for p in params]
        _step(ref_params, ref, grads, skip, lr0)
        _step(params, opt, grads, skip, lr0)
        _assert_close(ref_params, ref, params, opt)
        if skip is one:
            for p, b, m in zip(params, before, moments):
                assert torch.equal(p, b)
                for key, v in opt.state[p].items():
                    assert torch.equal(v, m[key]) if m else float(v.abs().sum()) == 0.0, key
    assert float(opt.state[params[0]]["step"]) == 7.0


@pytest.mark.parametrize("device", DEVICES)
def test_without_found_inf_and_with_groups_of_different_eps(device):
    ref_params, ref = _setup(device, torch.optim.Adam, fused=True)
    params, opt = _setup(device, OneLaunchAdam)
    for o in (ref, opt):
        o.param_groups[1]["eps"] = 1e-8
        o.param_groups[2]["betas"] = (0.8, 0.99)
    for k in range(4):
        _step(ref_params, ref, _grads(k, device))
        _step(params, opt, _grads(k, device))
    _assert_close(ref_params, ref, params, opt)


@pytest.mark.parametrize("device", DEVICES)
def test_state_dict_round_trip_continues_identically(device):
    params, opt = _setup(device, OneLaunchAdam)
    for k in range(3):
        _step(params, opt, _grads(k, device), torch.zeros((), device=device))
    buf = io.BytesIO()
    torch.save({"params": [p.detach() for p in params], "opt": opt.state_dict()}, buf)

    def restore(cls, **kw):
        buf.seek(0)  # a fresh copy each: load_state_dict keeps the loaded tensors, it does not copy them
        saved = torch.load(buf, weights_only=True)
        ps, o = _setup(device, cls, **kw)
        with torch.no_grad():
            for p, v in zip(ps, saved["params"]):
                p.copy_(v)
        o.load_state_dict(saved["opt"])
        return ps, o

    params2, opt2 = restore(OneLaunchAdam)
    params3, opt3 = restore(torch.optim.Adam, fused=True)  # the state layout is torch Adam's
    for k in range(3, 6):
        for ps, o in ((params, opt), (params2, opt2), (params3, opt3)):
            _step(ps, o, _grads(k, device), torch.zeros((), device=device))
    for p, p2 in zip(params, params2):
        assert torch.equal(p, p2)
        for key in opt.state[p]:
            assert torch.equal(opt.state[p][key], opt2.state[p2][key])
    _assert_close(params3, opt3, params, opt)


@pytest.mark.parametrize("device", DEVICES)
def test_replaced_parameters_get_a_new_update_buffer(device):
    """Density control swaps a parameter (and its state) for a bigger one between steps."""
    params, opt = _setup(device, OneLaunchAdam)
    ref_params, ref = _setup(device, torch.optim.Adam, fused=True)
    _step(params, opt, _grads(0, device))
    _step(ref_params, ref, _grads(0, device))
    for ps, o in ((params, opt), (ref_params, ref)):
        old = ps[0]
        new = torch.nn.Parameter(torch.cat((old.detach(), old.detach()[:5])))
        state = o.state.pop(old)
        state["exp_avg"] = torch.cat((state["exp_avg"], torch.zeros_like(state["exp_avg"][:5])))
        state["exp_avg_sq"] = torch.cat((state["exp_avg_sq"], torch.zeros_like(state["exp_avg_sq"][:5])))
        o.state[new] = state
        o.param_groups[0]["params"][0] = new
        ps[0] = new
    grads = _grads(1, device)
    grads[0] = torch.cat((grads[0], grads[0][:5]))
    _step(params, opt, grads)
    _step(ref_params, ref, grads)
    torch.testing.assert_close(params[0], ref_params[0], rtol=1e-6, atol=1e-6 * LRS[0])
    assert params[0].shape == (45, 3)


def test_one_step_is_six_operations_for_all_groups_and_no_sync():
    params, opt = _setup("cpu", OneLaunchAdam)
    _step(params, opt, _grads(0, "cpu"), torch.zeros(()))  # creates the state
    for p, g in zip(params, _grads(1, "cpu")):
        p.grad = g
    with OpCounter() as c:
        opt.step()
    kernels = {k: v for k, v in c.by_name.items() if not k.startswith("profiler::")}
    assert sum(kernels.values()) == 6, kernels
    assert c.syncs == 0


def test_weight_decay_and_tensor_lr_are_refused():
    p = torch.nn.Parameter(torch.zeros(3))
    with pytest.raises(ValueError, match="weight decay"):
        OneLaunchAdam([{"params": [p], "weight_decay": 0.1}])
    opt = OneLaunchAdam([p], lr=torch.tensor(0.1))
    p.grad = torch.ones(3)
    with pytest.raises(ValueError, match="lr"):
        opt.step()
