"""t2bs: text (or any character mesh) to an animatable blendshape rig (T2Bs, ICCV 2025)."""

from t2bs.openmp import choose_wait_policy as _choose_wait_policy

# Before torch loads: spin briefly when this process has the cores to itself, wait passively when they are busy
# (t2bs/openmp.py has the measurements); a user's own OMP_WAIT_POLICY / GOMP_SPINCOUNT wins.
_choose_wait_policy()

__version__ = "0.1.0"
