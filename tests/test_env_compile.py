"""``UAVEnv(compile_step=True)``: the torch.compile'd step gives the eager step's outputs."""

import pytest
import torch

from uavlae.envs import UAVEnv


def test_compile_step_is_off_by_default_and_not_torchrls_compile():
    env = UAVEnv(batch_size=[2], seed=0)
    assert not env.compiled
    env = UAVEnv(batch_size=[2], seed=0, compile_step=True)  # builds the wrapper, compiles nothing yet
    assert env.compiled
    # TorchRL's own ``compile=`` would have compiled the whole step_and_maybe_reset (resets too)
    assert env.__dict__.get("_compiled_step_and_maybe_reset") is None


# the first compile takes about 30 s on a loaded 2-core CPU (cold Inductor cache), then a few seconds
def test_compiled_step_matches_eager():
    b, steps = 8, 12
    eager = UAVEnv(batch_size=[b], seed=3)
    compiled = UAVEnv(batch_size=[b], seed=3, compile_step=True)
    td_e, td_c = eager.reset(), compiled.reset()
    gen = torch.Generator().manual_seed(0)
    n_done = 0
    # one graph for every step, partial resets included: a recompile is an error here
    with torch._dynamo.config.patch(error_on_recompile=True):
        for _ in range(steps):
            action = torch.rand(b, 2, generator=gen) * 2 - 1
            td_e["action"], td_c["action"] = action, action.clone()
            out_e, td_e = eager.step_and_maybe_reset(td_e)
            out_c, td_c = compiled.step_and_maybe_reset(td_c)
            n_done += int(out_e["next", "done"].sum())
            keys = sorted(out_e.keys(True, True), key=str)
            assert keys == sorted(out_c.keys(True, True), key=str)
            for k in keys:
                x, y = out_e[k], out_c[k]
                assert x.dtype == y.dtype and x.shape == y.shape, k
                if x.is_floating_point():
                    # Inductor's fused float32 math may differ from ATen's in the last bits
                    torch.testing.assert_close(y, x, rtol=1e-5, atol=1e-4, equal_nan=True, msg=str(k))
                else:  # events, flags, step counters, served GE: exactly equal
                    assert torch.equal(x, y), k


@pytest.mark.parametrize("blocked_fraction", [0.03, 0.5])  # within the compaction cap, and beyond it
def test_compiled_retry_matches_eager_sparse_retry(blocked_fraction):
    # inside the compiled CPU step the heading retries run on the blocked OUs compacted into
    # retry_capacity slots (or, past that, in the dense form): both give the eager retries
    from uavlae.envs import physics as ph

    g = torch.Generator().manual_seed(0)
    b, k, z, t = 512, 7, 6, 4
    pos = torch.rand(b, k, 2, generator=g) * 500
    vel = (torch.rand(b, k, 2, generator=g) * 2 - 1) * 10
    lo = torch.rand(b, z, 2, generator=g) * 450
    blocked = torch.cat([lo, lo + 20 + torch.rand(b, z, 2, generator=g) * 150], -1)
    mask = torch.rand(b, z, generator=g) < 0.7
    ok = torch.rand(b, k, generator=g) > blocked_fraction
    heads = torch.rand(t, b, k, generator=g) * (2 * torch.pi)
    n_bad = int((~ok).sum())
    assert (n_bad > ph.retry_capacity(b * k)) == (blocked_fraction > 0.1)
    eager = ph._retry(pos, vel, ok, heads, blocked, mask, 500.0, 500.0, 1.0)
    compiled = torch.compile(ph._retry, dynamic=False, fullgraph=True)(pos, vel, ok, heads, blocked, mask, 500.0, 500.0, 1.0)
    assert (eager[~ok] == 0).all(-1).sum() < n_bad  # some retries found a heading
    assert torch.equal(eager[~ok] == 0, compiled[~ok] == 0)  # the same OUs hover
    torch.testing.assert_close(compiled[~ok], eager[~ok], rtol=1e-5, atol=1e-4)


def test_compiled_step_matches_eager_step_by_step_at_scale():
    # the compiled CPU step runs the OU step and the GE service as C kernels (envs/ckernels.py):
    # from the same root and random state, one compiled step gives the eager step's events,
    # flags and integers exactly and its floats to rounding, over many OU retries and services
    b, steps = 256, 40
    eager = UAVEnv(batch_size=[b], seed=7)
    compiled = UAVEnv(batch_size=[b], seed=7, compile_step=True)
    td = eager.reset()
    gen = torch.Generator().manual_seed(0)
    served = 0
    for _ in range(steps):
        td["action"] = torch.rand(b, 2, generator=gen) * 2.4 - 1.2
        rng = eager.rng.get_state().clone()
        out_e = eager._step(td)
        compiled.rng.set_state(rng)
        out_c = compiled._step(td)
        for k in out_e.keys(True, True):
            x, y = out_e[k], out_c[k]
            if x.is_floating_point():
                torch.testing.assert_close(y, x, rtol=1e-5, atol=1e-4, equal_nan=True, msg=str(k))
            else:
                assert torch.equal(x, y), k
        served += int((out_e["state", "served_ge"] >= 0).sum())
        full = td.clone(False).set("next", out_e)
        td = eager.maybe_reset(eager._step_mdp(full))
    assert served > 0


@pytest.mark.parametrize("ego", [False, True])
def test_compiled_observation_kernel_gives_inductor_s_build_bit_for_bit(ego):
    # at B >= MIN_BATCH the compiled CPU step writes the observation (before the ego columns)
    # with ckernels.obs_cpu; with layout.c_kernel off it keeps Inductor's build: every output of
    # the two is equal, bit for bit, across steps and partial resets
    from uavlae.envs import ckernels
    from uavlae.envs.config import EnvConfig

    if not ckernels.load():
        pytest.skip("no C compiler: the compiled step keeps its torch code")
    b = ckernels.MIN_BATCH
    envs = [UAVEnv(EnvConfig(ego_features=ego), batch_size=[b], seed=5, compile_step=True) for _ in range(2)]
    envs[1].layout.c_kernel = False
    tds = [e.reset() for e in envs]
    gen = torch.Generator().manual_seed(0)
    done = 0
    for _ in range(10):
        action = torch.rand(b, 2, generator=gen) * 2 - 1
        outs = []
        for i, e in enumerate(envs):
            tds[i]["action"] = action.clone()
            out, tds[i] = e.step_and_maybe_reset(tds[i])
            outs.append(out)
        done += int(outs[0]["next", "done"].sum())
        for k in outs[0].keys(True, True):
            assert torch.equal(outs[0][k], outs[1][k]), k
        obs, ref = outs[0]["next", "observation"], outs[1]["next", "observation"]
        assert obs.shape == (b, envs[0].layout.size) and torch.equal(obs.signbit(), ref.signbit())
    assert done > 0
