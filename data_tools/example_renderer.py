"""A minimal out-of-process renderer speaking mcrecon's file protocol (a script in the clone).

Usage (mcrecon fills in the two paths)::

    mcrecon adapt --renderer-cmd "python data_tools/example_renderer.py {request} {reply}" \
        --size 64x64 --spp 16 --method box -o out.exr --log run.h5

The renderer itself is :mod:`mcrecon.renderers.example`, which the package
ships so that ``python -m mcrecon.renderers.example {request} {reply}``
runs from any directory; this script runs the same code by its path.
"""

import sys

from mcrecon.renderers.example import main, shade  # noqa: F401 -- tests import them from here

if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
