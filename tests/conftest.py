"""What every test shares: one torch thread, wandb offline, and one local LLM server per test
process (a pytest-xdist worker is one): its start costs about a minute on one core, so the files
that need it ask for the session's (``local_llm``; ``llm_server`` is the same server)."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("WANDB_MODE", "offline")

import torch  # noqa: E402

torch.set_num_threads(int(os.environ.get("UAVLAE_NUM_THREADS", "1")))


import pytest  # noqa: E402


@pytest.fixture(scope="session")
def local_llm():
    """The local llama.cpp server (SmolLM2-135M, one thread, one slot), started on first use and
    stopped at the end of the session, exactly its child."""
    from uavlae.llm.server import local_server

    with local_server(n_threads=1, n_parallel=1) as srv:
        yield srv
    with pytest.raises(ProcessLookupError):
        os.kill(srv.pid, 0)


@pytest.fixture(scope="session")
def llm_server(local_llm):
    return local_llm
