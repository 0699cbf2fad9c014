"""warp_vision: biomimetic active vision in a simulated human (ray-traced foveated eyes, liNets, MuJoCo body).

The subpackages, each importing only those before it: ``eye`` (optics, retinas, pupil), ``kernels`` (the
Warp ray tracer and the liNet op, each beside a plain reference), ``scene`` (what is rendered), ``nn``
(liNets and the other nets), ``body`` (the MuJoCo body), ``data`` (self-synthesised datasets), ``sim``
(the closed loop), ``train`` (every net's training) and ``bench``. docs/ARCHITECTURE.md maps them
module by module; ``python -m warp_vision`` lists the commands.
"""

import os as _os

# Warp's CPU kernels run on the same cores as torch's OpenMP pool. With the default wait policy
# libgomp's idle workers spin after every parallel torch op and steal the cores the split Warp
# launches need (its effect on the liNet forward: docs/RESULTS.md, "Design choices measured").
# This takes effect only when warp_vision is imported before torch; set the variable yourself to
# choose otherwise.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def __getattr__(name: str):
    # __version__ read on first use: the distribution metadata lookup (~20 ms with its imports) stays off
    # the import of every module of the package
    if name == "__version__":
        from warp_vision.provenance import package_version

        return package_version()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
