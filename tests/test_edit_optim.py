"""The edit's Adam: torch's fused Adam update on state it keeps itself, without importing torch._dynamo."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from virgi_ns.edit.optim import EditAdam


def _loss(ps):
    return (ps[0] ** 3).sum() + (ps[1] * ps[0].sum(0)).sum()


def _run(make, steps=6):
    g = torch.Generator().manual_seed(0)
    ps = [torch.randn(5, 3, generator=g).requires_grad_(), torch.randn(3, generator=g).requires_grad_()]
    opt = make(ps)
    for _ in range(steps):
        opt.zero_grad()
        _loss(ps).backward()
        opt.step()
    return ps, opt


def test_edit_adam_is_torch_adam():
    """The same parameters, step for step, as torch.optim.Adam with its fused kernel (and close to its
    default implementation)."""
    ours, _ = _run(lambda ps: EditAdam(ps, lr=0.02))
    fused, _ = _run(lambda ps: torch.optim.Adam(ps, lr=0.02, fused=True))
    plain, _ = _run(lambda ps: torch.optim.Adam(ps, lr=0.02))
    for a, b, c in zip(ours, fused, plain):
        torch.testing.assert_close(a, b, atol=0, rtol=0)
        torch.testing.assert_close(a, c, atol=1e-6, rtol=1e-6)
        assert float((a - b).detach().abs().max()) == 0.0


def test_a_restarted_edit_adam_steps_as_a_fresh_one():
    ps, opt = _run(lambda ps: EditAdam(ps, lr=0.05), steps=3)
    state = opt.state_tensors()
    start = [p.detach().clone() for p in ps]
    opt.restart()
    assert all(t is u for t, u in zip(opt.state_tensors(), state))  # in place
    assert all(float(t.abs().max()) == 0.0 for t in state)
    fresh_ps = [p.clone().requires_grad_() for p in start]
    fresh = EditAdam(fresh_ps, lr=0.05)
    for o, q in ((opt, ps), (fresh, fresh_ps)):
        o.zero_grad()
        _loss(q).backward()
        o.step()
    for a, b in zip(ps, fresh_ps):
        torch.testing.assert_close(a, b, atol=0, rtol=0)


def test_edit_adam_does_not_import_the_compiler():
    """Building and stepping it in a fresh interpreter leaves torch._dynamo unimported (torch.optim's
    optimizers import it: about a second of a fresh process)."""
    code = ("import sys, torch\n"
            "from virgi_ns.edit.optim import EditAdam\n"
            "p = torch.zeros(3, requires_grad=True)\n"
            "o = EditAdam([p], lr=0.1)\n"
            "(p * torch.arange(3.0)).sum().backward(); o.step()\n"
            "assert float(p[1]) < 0, p\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


@pytest.mark.parametrize("hold", [0, 3])
def test_a_cosine_decay_steps_by_half_a_cosine_to_zero_then_stops(hold):
    """With a constant gradient, Adam's bias-corrected step is exactly its learning rate, so the
    parameter walks by the sum of the schedule: lr for the ``hold`` first steps, then
    lr (1 + cos(pi k / n)) / 2 for k = 0..n-1, and not at all after that. Also through torch.optim.Adam
    (the fallback, which sets the rate on the host)."""
    import math

    n, lr = 8, 0.1
    rates = [lr] * hold + [0.5 * lr * (1 + math.cos(math.pi * k / n)) for k in range(n)] + [0.0] * 3
    expected = [-sum(rates[: k + 1]) for k in range(len(rates))]
    for fallback in (False, True):
        p = torch.zeros(2, requires_grad=True)
        opt = EditAdam([p], lr=lr, decay_steps=n, hold_steps=hold)
        if fallback:
            opt._fallback = torch.optim.Adam([p], lr=lr)
        walked = []
        for _ in range(len(rates)):
            opt.zero_grad()
            p.sum().backward()
            opt.step()
            walked.append(float(p[0]))
        assert walked == [pytest.approx(e, abs=1e-6) for e in expected], fallback
        last = hold + n - 1  # the last step that moves
        assert walked[last + 1] == pytest.approx(walked[last], abs=1e-7) and walked[-1] == pytest.approx(walked[last], abs=1e-7)
        opt.restart()  # a restart starts the schedule again: the next step is the full rate
        before = float(p[0])
        opt.zero_grad()
        p.sum().backward()
        opt.step()
        assert float(p[0]) - before == pytest.approx(-lr, abs=1e-6)
    with pytest.raises(ValueError, match="decay_steps"):
        EditAdam([p], lr=lr, decay_steps=0)
    with pytest.raises(ValueError, match="hold_steps"):
        EditAdam([p], lr=lr, hold_steps=2)  # a hold without a decay


@pytest.mark.parametrize("decay", [None, 6])
def test_each_parameters_rate_is_scaled_by_its_factor(decay):
    """``scales``: with a constant gradient each parameter walks by the sum of the schedule times its
    own factor (fused kernel, one call per factor, and the torch.optim fallback alike); a factor of 1
    steps as without scales, bit for bit."""
    import math

    lr, n = 0.1, 6
    rates = [lr] * n if decay is None else [0.5 * lr * (1 + math.cos(math.pi * k / n)) for k in range(n)]
    for fallback in (False, True):
        ps = [torch.zeros(2, requires_grad=True) for _ in range(3)]
        opt = EditAdam(ps, lr=lr, decay_steps=decay, scales=[1.0, 2.5, 1.0])
        if fallback:
            groups = [{"params": [ps[0], ps[2]], "scale": 1.0}, {"params": [ps[1]], "scale": 2.5}]
            opt._fallback = torch.optim.Adam(groups, lr=lr)
        alone = torch.zeros(2, requires_grad=True)
        plain = EditAdam([alone], lr=lr, decay_steps=decay)
        if fallback:
            plain._fallback = torch.optim.Adam([alone], lr=lr)
        for _ in range(n):
            for o, q in ((opt, ps), (plain, [alone])):
                o.zero_grad()
                sum(x.sum() for x in q).backward()
                o.step()
        assert float(ps[0][0]) == pytest.approx(-sum(rates), abs=1e-6), fallback
        assert float(ps[1][0]) == pytest.approx(-2.5 * sum(rates), abs=1e-6), fallback
        assert torch.equal(ps[0], ps[2]) and torch.equal(ps[0].detach(), alone.detach())
    for bad in ([1.0], [1.0, 0.0, 1.0], [1.0, -2.0, 1.0]):
        with pytest.raises(ValueError, match="scales"):
            EditAdam(ps, lr=lr, scales=bad)
