"""``UAVEnv(compile_step=True)``: the torch.compile'd step gives the eager step's outputs."""

import torch
from torchrl.envs.utils import step_mdp

from uavlae.envs import UAVEnv


def test_compile_step_is_off_by_default_and_not_torchrls_compile():
    env = UAVEnv(batch_size=[2], seed=0)
    assert not env.compiled
    env = UAVEnv(batch_size=[2], seed=0, compile_step=True)  # builds the wrapper, compiles nothing yet
    assert env.compiled
    # TorchRL's own ``compile=`` would have compiled the whole step_and_maybe_reset (resets too)
    assert env.__dict__.get("_compiled_step_and_maybe_reset") is None


# the first compile is the slow part (a cold Inductor cache); the later ones reuse it
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


def test_compiled_step_matches_eager_step_by_step_at_scale():
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
        td = eager.maybe_reset(step_mdp(full, keep_other=False, exclude_action=True))
    assert served > 0


def test_ego_frame_observation_compiles_in_one_graph():
    # the ego frame's sorts and gathers compile without a graph break (fullgraph) and give the
    # eager columns; compiling the observation alone costs a fraction of the whole step's compile
    env = UAVEnv({"obs_frame": "ego"}, batch_size=[8], seed=3)
    td = env.rollout(3, break_when_any_done=False)
    state = {k: v[:, -1] for k, v in td["next", "state"].items()}
    compiled = torch.compile(env.layout.build, fullgraph=True)
    torch.testing.assert_close(compiled(state), env.layout.build(state), rtol=1e-5, atol=1e-5)
