"""Suite-wide set-up: the tests run as they would from a plain interactive shell.

- Several tests send Ctrl-C (SIGINT) to this process, or to processes it starts, and check that a
  run stops as interrupted. A shell starts a background job (`make test &` in a script without
  job control, `nohup`) with SIGINT ignored, Python then installs no KeyboardInterrupt handler,
  and a child inherits the ignored signal through exec: those tests would fail there although the
  pipeline does the right thing (a run started with Ctrl-C ignored is not stopped by it). The
  suite gets Python's own handler, as an interactive start has it; a child started from here then
  gets the default disposition back.
- The pipeline reads its defaults from the environment: `PIPELINE_DATASET`, `PIPELINE_CACHE`,
  `PIPELINE__SECTION__KEY` settings and `DASK_SCHEDULER_ADDRESS`. A user's shell that sets them
  for their own runs would change what the tests run (another dataset, epochs, a cluster) and fail
  them; the tests that exercise those variables set them themselves.
"""
import os
import signal

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

for _name in [n for n in os.environ if n.startswith("PIPELINE_") or n == "DASK_SCHEDULER_ADDRESS"]:
    del os.environ[_name]


import pytest  # noqa: E402  (after the signal and environment set-up above, which must come first)


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory):
    """The 10-frame synthetic world (seed 5, 640 x 384, one sequence) that many tests run the
    pipeline on, generated once per session (about 3 s each time otherwise); a test copies it
    (shutil.copytree) where it may change it, and so that each cache records a world of its own."""
    from pipeline.world import generate

    root = tmp_path_factory.mktemp("tiny-world") / "world"
    generate(root, frames=10, seed=5, resolution_wh=(640, 384), sequence_len=10)
    return root
