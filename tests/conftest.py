"""Suite-wide set-up.

Several tests send Ctrl-C (SIGINT) to this process, or to processes it starts, and check that a
run stops as interrupted. A shell starts a background job (`make test &` in a script without job
control, `nohup`) with SIGINT ignored, Python then installs no KeyboardInterrupt handler, and a
child inherits the ignored signal through exec: those tests would fail there although the
pipeline does the right thing (a run started with Ctrl-C ignored is not stopped by it). Give the
suite Python's own handler, as an interactive start has it; a child started from here then gets
the default disposition back.
"""
import signal

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
