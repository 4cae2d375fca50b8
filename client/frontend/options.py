"""Options of the stereo(-inertial) ORB front-end."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FrontendOptions:
    """Tuning of the front-end.  Pixel thresholds are at octave 0 and scale with ``1.2**octave``."""

    # ORB extraction
    n_features: int = 1000  # at 640x480; smaller images get proportionally fewer (min 300)
    scale_features_with_resolution: bool = True
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 20
    min_fast_threshold: int = 5
    # cells with < 1/4 of their share of corners detected again at a noise-derived threshold; off: on a
    # clear world it tripled the UGV's keyframes and its error (docs/decisions.md, issue 28)
    fast_cell_refill: bool = False
    low_contrast_std: float = 20.0  # below this grey-level std: contrast step + blur (dim/fog); 0 = off
    contrast: str = "stretch"  # stretch | clahe | off (see features.ContrastNormaliser)
    clahe_clip_limit: float = 2.0
    max_contrast_gain: float = 4.0  # stretch only
    grid_cols: int = 8
    grid_rows: int = 6
    # stereo (LK refinement + row check on rectified coordinates)
    stereo_max_row_error_px: float = 1.0
    stereo_fb_error_px: float = 0.5
    stereo_min_depth_m: float = 0.3
    close_depth_baselines: float = 40.0  # ORB-SLAM's ThDepth: closer points are created from one stereo pair
    stereo_residual_max_depth_baselines: float = 400.0  # beyond this a keypoint's disparity is ignored
    # tracking
    search_radius_px: float = 15.0
    local_search_radius_px: float = 4.0
    max_descriptor_distance: int = 80
    ratio: float = 0.9
    min_tracked: int = 20
    pnp_reprojection_px: float = 3.0
    local_map_keyframes: int = 10
    # keyframes
    kf_min_tracked_ratio: float = 0.75
    kf_min_close_tracked: int = 70
    kf_max_interval_s: float = 0.5
    kf_min_interval_frames: int = 0
    # local mapping
    ba_window: int = 10
    ba_fixed_max: int = 10
    ba_min_shared: int = 15  # fewer points in common: not covisible (neither in the window nor fixed)
    ba_iterations: int = 6
    # a point's refined position is streamed when it moved this far since it was last sent: the server's
    # copy stays within it of the agent's, a tenth of place recognition's smallest 3-D tolerance, and
    # about half of local BA's updates move a point by less
    point_update_min_m: float = 0.001
    triangulation_neighbours: int = 3
    min_parallax_cos: float = 0.9998
    culling_min_found_ratio: float = 0.25
    redundant_kf_ratio: float = 0.9
    # relocalisation / loss
    reloc_keyframes: int = 20
    reloc_min_inliers: int = 30
    reloc_bow_candidates: int = 5  # older keyframes found by bag of words, besides the recent ones
    max_lost_frames: int = 20  # without an IMU (or before gravity alignment): then a new session
    imu_hold_s: float = 3.0  # with an IMU: IMU-only propagation this long before a new session
    # with an IMU, a lost frame with enough close stereo points becomes a keyframe at the IMU's pose
    # (at most one per interval), so tracking resumes on its points (ORB-SLAM3's ``InsertKFsLost``)
    imu_lost_keyframes: bool = True
    imu_lost_keyframe_interval_s: float = 0.2
    imu_lost_keyframe_min_points: int = 100  # stereo points, as a keyframe makes at least
    # tracking quality: OK from this many inliers, WEAK from ``min_tracked``
    good_min_inliers: int = 50
    # what weak or lost tracking adds to the next keyframe's pose error relative to the previous keyframe
    # (``Keyframe.odom_sigma``), in quadrature per frame: a weak frame's pose passed only the IMU gate;
    # a lost stretch adds what the IMU propagation added since the last visual pose when tracking
    # resumes (``MotionFilter.growth_sigmas``), this per frame without an IMU
    odom_weak_sigma_m: float = 0.3
    odom_weak_sigma_deg: float = 1.0
    odom_lost_sigma_m: float = 0.5
    odom_lost_sigma_deg: float = 2.0
    # imu
    gravity_init_s: float = 1.0
    # visual-inertial tracking: the IMU's pose prediction as a prior in the frame-to-map refinement,
    # and its gate (chi2, 6 DoF, 99.9%): a visual pose beyond it is not taken
    imu_prior: bool = True
    imu_gate_chi2: float = 22.46
    imu_gate_strong_scale: float = 25.0  # from ``good_min_inliers`` inliers the gate is this much wider
    imu_gate_rot_chi2: float = 16.27  # the attitude alone (3 DoF, 99.9%), whatever the inliers
    vio_meas_sigma_m: float = 0.02  # a visual body position, as the filter's measurement
    vio_init_vel_sigma_mps: float = 0.3
    vio_init_acc_sigma_mps2: float = 0.2
    vio_acc_noise: float = 0.1  # unmodelled acceleration (m/s^2 per sqrt(Hz)): vibration, timing
    vio_acc_correction_walk: float = 0.02  # random walk of the world acceleration correction
    vio_rot_sigma_deg: float = 0.5  # attitude after a visual pose
    vio_gyro_drift_dps: float = 0.5  # attitude uncertainty growth while the IMU alone holds it
    gyro_bias_time_s: float = 3.0  # averaging time of the gyro bias estimate
    gyro_bias_max_step_dps: float = 3.0  # larger frame-to-frame gyro/visual disagreement: not a bias
    # visual-inertial local BA (ORB-SLAM3's): preintegrated IMU terms between consecutive keyframes,
    # velocity and bias states; the bias priors (1 sigma about each run's start) only keep them bounded.
    # Off: measured worse than the visual-only BA on factory01's UGV (docs/decisions.md, issue 28)
    vi_ba: bool = False
    # other agents' marker carriers (a dataset's markers.yaml) masked out of ORB and stereo: they move
    # (frontend.carrier_mask); margin (px) and frames a missed carrier stays masked
    carrier_mask: bool = True
    carrier_mask_margin_px: int = 6
    carrier_mask_hold_frames: int = 4
    carrier_mask_full_every: int = 2  # frames between whole-image carrier searches (around masks between)
    vi_ba_gyro_bias_sigma: float = 0.05  # rad/s
    vi_ba_acc_bias_sigma: float = 0.5  # m/s^2
