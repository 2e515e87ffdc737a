#!/usr/bin/env python
"""Which cause breaks a later torch.cuda.make_graphed_callables re-capture? (docs/gpu.md, "Re-capturing")

Mimics rmavatar's StepGraphs with torch only: piece A ("posing", an nn.Module whose parameters are all
of the avatar's) captured; piece B ("losses", a plain function that also takes A's parameter `means` as
an input) captured from A's outputs; eager steps (A replay -> eager op -> B replay -> loss.backward() on
the default stream -> fused Adam); then A captured again with an op set that changes, in particular one
that starts using `sh_rest`, a parameter unused at the first capture (SH degree 0 -> 1).

    python scripts/gpu_recapture_probe.py            # every variant, each in its own process (~1-2 min), a table
    python scripts/gpu_recapture_probe.py VARIANT    # one variant, prints RESULT {...}
    PROBE_DRY_CPU=1 python scripts/gpu_recapture_probe.py VARIANT   # logic self-test without CUDA (no graphs)

Reading the table (expected on torch 2.11 if the stale default-stream AccumulateGrad is the cause):
  same_ops / new_cublas / degree1_first OK  -> re-capturing as such, and cuBLAS first used in a
                                               re-capture, are fine
  unused_kept FAIL, unused_dropped OK       -> the cause is a default-stream AccumulateGrad node of a
                                               parameter first used in the re-capture, kept alive
  unused_hook FAIL, unused_hook_weakref OK  -> gsplat_backend's means2d hook closure is what keeps it alive
  *_pin_capture / *_pin_side / *_side_steps / *_override OK -> those fixes work
"""
from __future__ import annotations

import contextlib
import gc
import json
import os
import subprocess
import sys
import time
import warnings
import weakref

import torch
from torch import nn

DRY = os.environ.get("PROBE_DRY_CPU") == "1"
DEV = "cpu" if DRY else "cuda"
N = 4096
MISMATCH = "AccumulateGrad node's stream does not match"

# name: (config, expected on torch 2.11 under the stale-default-stream hypothesis)
VARIANTS = {
    "same_ops":              (dict(first=0, second=0, window=True), "OK"),
    "new_cublas":            (dict(first=0, second=0, mm=True), "OK"),
    "degree1_first":         (dict(first=1, second=1, window=True), "OK"),
    "unused_kept":           (dict(first=0, second=1), "FAIL"),
    "unused_dropped":        (dict(first=0, second=1, keep=False), "OK"),
    "unused_hook":           (dict(first=0, second=1, keep=False, hook="closure"), "FAIL"),
    "unused_hook_weakref":   (dict(first=0, second=1, keep=False, hook="weakref"), "OK"),
    "unused_kept_sync_empty": (dict(first=0, second=1, sync_empty=True), "FAIL"),
    "unused_kept_pin_capture": (dict(first=0, second=1, pin="capture"), "OK"),
    "unused_kept_pin_side":  (dict(first=0, second=1, pin="side"), "OK"),
    "unused_kept_side_steps": (dict(first=0, second=1, side_steps=True), "OK"),
    "unused_kept_override":  (dict(first=0, second=1, override=True), "OK (needs torch with the flag)"),
}


class Core(nn.Module):
    """The avatar: all parameters. Host switches decide the op set (what a capture fixes)."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.means = nn.Parameter(torch.randn(N, 3, generator=g))
        self.mix = nn.Parameter(torch.eye(3) + 0.1 * torch.randn(3, 3, generator=g))
        self.sh_dc = nn.Parameter(torch.rand(N, 1, 3, generator=g))
        self.sh_rest = nn.Parameter(0.01 * torch.randn(N, 3, 3, generator=g))  # degree 1: 3 more bands
        self.degree, self.mm, self.window = 0, False, False


class Posing(nn.Module):
    """Piece A, a fresh wrapper per capture (as rmavatar's _Posing): its parameters are all of Core's."""

    def __init__(self, core: Core):
        super().__init__()
        self.core = core

    def forward(self, x, campos):
        c = self.core
        if c.mm:  # cuBLAS (bmm) used for the first time in this process, inside a re-capture
            pos = torch.bmm((x + c.means).unsqueeze(1), c.mix.expand(N, 3, 3)).squeeze(1)
        else:  # elementwise only: no cuBLAS anywhere before
            pos = (x + c.means) * c.mix.diagonal()
        if c.window:
            pos = pos * 1.0001
        if c.degree == 0:  # sh_rest unused (allow_unused_input=True gives it a None grad)
            colors = torch.clamp_min(c.sh_dc[:, 0] * 0.2820948 + 0.5, 0.0)
        else:  # view-dependent: uses sh_rest and pos
            d = torch.nn.functional.normalize(pos - campos, dim=-1)
            basis = torch.cat((torch.ones_like(d[:, :1]), d), 1)  # [N,4]
            sh = torch.cat((c.sh_dc, c.sh_rest), 1)  # [N,4,3]
            colors = torch.clamp_min((basis.unsqueeze(-1) * sh).sum(1) * 0.2820948 + 0.5, 0.0)
        return pos, colors


def losses(img, target, means):
    """Piece B: takes A's parameter `means` as an input (as rmavatar's _Losses)."""
    return ((img - target) ** 2).mean() + 1e-3 * means.square().mean()


def raster(pos, colors, hook):
    """The eager op between the pieces; hook: gsplat_backend.py's means2d pattern."""
    img = colors * torch.sigmoid(pos[:, :1])
    info = {}
    if hook:
        m2d_c = (pos[:, :2] * 1.0).unsqueeze(0)  # gsplat's batched means2d [1,N,2]
        m2d = m2d_c[0]
        m2d.retain_grad()
        if hook == "closure":  # as rmavatar/render/gsplat_backend.py:57-63: the closure holds means2d
            def _copy(grad):
                g = grad[0].detach()
                m2d.grad = g.clone() if m2d.grad is None else m2d.grad + g
        else:  # the fix: a weak reference, no cycle through the C++ graph
            ref = weakref.ref(m2d)

            def _copy(grad):
                t = ref()
                if t is not None:
                    g = grad[0].detach()
                    t.grad = g.clone() if t.grad is None else t.grad + g
        m2d_c.register_hook(_copy)
        img = img + 0.0 * m2d_c[0].sum(-1, keepdim=True)
        info["means2d"] = m2d
    return img, info


class Tag:
    pass


def graphed(fn, sample):
    if DRY:
        return _fake_graphed(fn, len(sample))
    return torch.cuda.make_graphed_callables(fn, sample, num_warmup_iters=2, allow_unused_input=True)


def _fake_graphed(fn, n_user):
    """DRY self-test only: like make_graphed_callables' Graphed function, an autograd node with edges to
    the user inputs and to every module parameter (used or not), but eager."""
    params = tuple(fn.parameters()) if isinstance(fn, nn.Module) else ()

    class Fake(torch.autograd.Function):
        @staticmethod
        def forward(ctx, *inputs):
            with torch.enable_grad():
                leaves = [t.detach().requires_grad_(t.requires_grad) for t in inputs[:n_user]]
                outs = fn(*leaves)
            outs = outs if isinstance(outs, tuple) else (outs,)
            ctx.outs, ctx.leaves = outs, leaves
            return tuple(o.detach() for o in outs)

        @staticmethod
        def backward(ctx, *grads):
            wrt = [t for t in ctx.leaves if t.requires_grad] + list(params)
            got = iter(torch.autograd.grad(ctx.outs, wrt, grads, allow_unused=True))
            user = [next(got) if t.requires_grad else None for t in ctx.leaves]
            return (*user, *got)

    def call(*args):
        out = Fake.apply(*args, *params)
        return out if isinstance(fn, nn.Module) else out[0]
    return call


def stream_ctx(s):
    return contextlib.nullcontext() if (DRY or s is None) else torch.cuda.stream(s)


def sync():
    if not DRY:
        torch.cuda.synchronize()


def chain(e):
    out = []
    while e is not None and len(out) < 6:
        text = str(e).strip()
        out.append(f"{type(e).__name__}: {text.splitlines()[0] if text else ''}")
        e = e.__cause__ or e.__context__
    return " <- ".join(out)


def run(name: str) -> dict:
    cfg = VARIANTS[name][0]
    keep, hook = cfg.get("keep", True), cfg.get("hook")
    res = {"variant": name, "torch": torch.__version__}
    warnings.simplefilter("always")
    caught = warnings.catch_warnings(record=True)
    seen = caught.__enter__()
    core = Core().to(DEV)
    core.degree = cfg["first"]
    opt = torch.optim.Adam(core.parameters(), lr=1e-3, fused=not DRY)
    g = torch.Generator(device=DEV).manual_seed(1)
    x = torch.randn(N, 3, device=DEV, generator=g)
    campos = torch.randn(3, device=DEV, generator=g)
    target = torch.rand(N, 3, device=DEV, generator=g)

    pins = None
    if cfg.get("pin"):  # fix: every parameter's AccumulateGrad made (and held) on a non-default stream
        if cfg["pin"] == "capture":
            torch.cuda.graph(torch.cuda.CUDAGraph())  # its __init__ makes the shared capture stream
            pin_stream = torch.cuda.graph.default_capture_stream
        else:
            pin_stream = torch.cuda.Stream()
        with stream_ctx(pin_stream):
            pins = [p.view_as(p).grad_fn.next_functions[0][0] for p in core.parameters()]
    step_stream = torch.cuda.Stream() if cfg.get("side_steps") and not DRY else None

    gA = graphed(Posing(core), (x.clone(), campos.clone()))
    state = {"gB": None, "tag": None}

    def step():
        if step_stream is not None:
            step_stream.wait_stream(torch.cuda.current_stream())
        with stream_ctx(step_stream):
            pos, colors = gA(x, campos)
            # tag sh_rest's AccumulateGrad (an edge of A's Graphed node) to see whether it outlives the step
            for fn, _ in pos.grad_fn.next_functions:
                if fn is not None and getattr(fn, "variable", None) is core.sh_rest:
                    if "tag" not in fn.metadata:
                        fn.metadata["tag"] = Tag()
                    state["tag"] = weakref.ref(fn.metadata["tag"])
            img, info = raster(pos, colors, hook)
            if state["gB"] is None:
                state["gB"] = graphed(losses, (img.detach().clone().requires_grad_(), target.clone(),
                                               core.means.detach().clone().requires_grad_()))
            loss = state["gB"](img, target, core.means)
            loss.backward()
            rest = core.sh_rest.grad
            state["rest_grad"] = None if rest is None else float(rest.abs().sum())
            state["loss"] = float(loss.detach())  # a sync: fine here
            opt.step()
            opt.zero_grad(set_to_none=True)
        if step_stream is not None:
            torch.cuda.current_stream().wait_stream(step_stream)
        return (pos, img, loss, info) if keep else None

    held = None
    mem0 = None
    for i in range(6):
        held = step()
        if i == 1 and not DRY:
            sync()
            mem0 = torch.cuda.memory_allocated()
    sync()
    if mem0 is not None:
        res["mem_growth_per_step_B"] = (torch.cuda.memory_allocated() - mem0) // 4
    gc.collect()
    res["sh_rest_eager_accumulator_alive_at_recapture"] = state["tag"] is not None and state["tag"]() is not None
    res["mismatch_warning_before"] = any(MISMATCH in str(w.message) for w in seen)

    # the switch: old callable dropped, gc collected then disabled (as rmavatar's no_collection)
    core.degree, core.mm, core.window = cfg["second"], cfg.get("mm", False), cfg.get("window", False)
    if cfg.get("override"):
        fn = getattr(torch.autograd.graph, "set_override_stale_capture_stream", None)
        if fn is None:
            res.update(result="SKIP", error="this torch has no set_override_stale_capture_stream")
            caught.__exit__(None, None, None)
            return res
        fn(True)
    if cfg.get("sync_empty") and not DRY:
        torch.cuda.synchronize()
        torch.cuda.empty_cache()
    gA = None
    gc.collect()
    gc.disable()
    t0 = time.perf_counter()
    try:
        gA = graphed(Posing(core), (x.clone(), campos.clone()))
        res["result"] = "OK"
    except Exception as exc:  # noqa: BLE001
        res.update(result="FAIL", error=chain(exc))
        with contextlib.suppress(Exception):
            sync()
    finally:
        gc.enable()
    res["recapture_s"] = round(time.perf_counter() - t0, 2)
    if res["result"] == "OK":
        try:  # replay works and the newly used parameter gets its gradient
            for _ in range(2):
                step()
            sync()
            ok = state["loss"] == state["loss"] and (core.degree == 0 or (state["rest_grad"] or 0) > 0)
            res["replay"] = "OK" if ok else f"BAD (loss {state['loss']}, sh_rest grad {state['rest_grad']})"
        except Exception as exc:  # noqa: BLE001
            res["replay"] = "FAIL " + chain(exc)
    res["mismatch_warning_any"] = any(MISMATCH in str(w.message) for w in seen)
    caught.__exit__(None, None, None)
    del held, pins
    return res


def main():
    if len(sys.argv) > 1:
        name = sys.argv[1]
        if not DRY and not torch.cuda.is_available():
            print("RESULT " + json.dumps({"variant": name, "result": "SKIP", "error": "no CUDA"}))
            return
        print("RESULT " + json.dumps(run(name)), flush=True)
        return
    print(f"torch {torch.__version__}, cuda {torch.version.cuda}, "
          f"{torch.cuda.get_device_name() if torch.cuda.is_available() else 'no GPU'}, "
          f"override flag: {hasattr(torch.autograd.graph, 'set_override_stale_capture_stream')}", flush=True)
    fmt = "{:<26} {:<9} {:<6} {:<7} {:<6} {:<8} {}"
    print(fmt.format("variant", "expected", "result", "replay", "stale", "warning", "first error (outermost <- cause)"))
    for name, (_, expected) in VARIANTS.items():
        t0 = time.perf_counter()
        try:
            p = subprocess.run([sys.executable, __file__, name], capture_output=True, text=True, timeout=150)
            lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
            r = json.loads(lines[-1][7:]) if lines else {
                "result": f"CRASH rc={p.returncode}", "error": (p.stderr.strip().splitlines() or [""])[-1]}
        except subprocess.TimeoutExpired:
            r = {"result": "TIMEOUT"}
        print(fmt.format(name, expected.split()[0], r.get("result", "?"), str(r.get("replay", "-"))[:7],
                         str(r.get("sh_rest_eager_accumulator_alive_at_recapture", "-"))[:6],
                         str(r.get("mismatch_warning_any", "-"))[:8], r.get("error", "")[:220]), flush=True)
        if r.get("mem_growth_per_step_B"):
            print(f"{'':26} memory growth per eager step: {r['mem_growth_per_step_B']} B "
                  f"({time.perf_counter() - t0:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
