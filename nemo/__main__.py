import sys

from nemo.worker import forward

code = forward(sys.argv[1:])  # a warm worker started by the workflow, if there is one
if code is None:
    from nemo.cli import main

    code = main()
raise SystemExit(code)
