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
