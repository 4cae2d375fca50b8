"""The second stage's co-location priors from a server correction, replacing the previous ones of the
same front-end session in one update."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.second_stage.factors import _diag, _gaussian, _key, _okey

if TYPE_CHECKING:
    from hivemap.client.second_stage.stage import SecondStage

F64 = NDArray[np.float64]


def set_colocations(
    st: SecondStage, priors: dict[int, tuple[F64, F64]], enu: bool = False, scope: set[int] | None = None
) -> None:
    """``SecondStage.set_colocations`` (see there)."""
    gtsam = st._gtsam
    sig = st.options.colocation_offset_sigma

    def in_scope(k: int) -> bool:
        return scope is None or k in scope

    factors, owners = [], []
    for kf_id, (pose, cov) in priors.items():
        if kf_id not in st._kfs or not in_scope(kf_id):
            continue
        T = gtsam.Pose3(np.asarray(pose, dtype=np.float64).reshape(4, 4))
        noise = _gaussian(np.asarray(cov).reshape(6, 6))
        if sig is None:
            factors.append(gtsam.PriorFactorPose3(_key(kf_id), T, noise))
        else:
            factors.append(gtsam.BetweenFactorPose3(_okey(), _key(kf_id), T, noise))
        owners.append(kf_id)
    old = [st._colocation_handle.pop(k) for k in list(st._colocation_handle) if in_scope(k)]
    st._colocation_enu = enu
    # this agent's fixes the server already fused (options.colocation_enu_holds_own_fixes)
    restore: list[Any] = []
    if enu and owners and st.options.colocation_enu_holds_own_fixes:
        pos = {k: i for i, k in enumerate(st._order)}
        last = max(pos[k] for k in owners)
        for kf_id in [k for k in st._gnss_handles if pos[k] <= last and in_scope(k)]:
            hs = st._gnss_handles.pop(kf_id)
            st._gnss_held[kf_id] = [st._factors[h] for h in hs]
            old += hs
    elif not enu and st._gnss_held:
        for kf_id in [k for k in st._gnss_held if in_scope(k)]:
            restore += [(kf_id, f) for f in st._gnss_held.pop(kf_id)]
    factors += [f for _, f in restore]
    if not factors and not old:
        return
    extra = None
    n_own = len(owners)
    sig_enu = st.options.colocation_offset_sigma_enu
    # the sigmas of O's prior for these priors (None: no O)
    s3 = None if sig is None else sig_enu if enu and sig_enu is not None else sig
    use_enu = s3 is not sig
    if s3 is not None and factors and (st._offset_prior is None or st._offset_prior[1] != use_enu):
        # the offset's prior: identity, tilt/yaw/translation sigmas (the ENU ones with ENU priors)
        if st._offset is None:
            extra = gtsam.Values()
            extra.insert(_okey(), gtsam.Pose3())
            st._offset = np.eye(4)
        if st._offset_prior is not None:
            old.append(st._offset_prior[0])
        factors.append(
            gtsam.PriorFactorPose3(
                _okey(), gtsam.Pose3(), _diag(np.array([s3[0], s3[0], s3[1]] + [s3[2]] * 3))
            )
        )
    handles = st._commit(factors, {}, remove=old, extra_values=extra)
    st._colocation_handle.update(zip(owners, handles[:n_own], strict=True))
    n_restore = len(restore)
    for (kf_id, _), h in zip(restore, handles[n_own : n_own + n_restore], strict=True):
        st._gnss_handles.setdefault(kf_id, []).append(h)
    if len(handles) > n_own + n_restore:
        st._offset_prior = (handles[n_own + n_restore], use_enu)
