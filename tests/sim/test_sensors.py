"""IMU and GNSS models against the true trajectory (paper Tables 2 and 3)."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.sim.dataset import cached_world
from hivemap.sim.scenarios import GnssNoise, ImuNoise, get_scenario
from hivemap.sim.sensors import (
    GeodeticOrigin,
    enu_to_geodetic,
    format_gpgga,
    geodetic_to_enu,
    integrate_imu,
    parse_gpgga,
    simulate_gnss,
    simulate_imu,
)
from hivemap.sim.trajectories import plan_trajectories


@pytest.fixture(scope="module")
def trajs():
    sc = get_scenario("factory01")
    return plan_trajectories(cached_world(sc.seed, sc.world_size_m), sc).trajectories


@pytest.mark.parametrize("agent", ["uav1", "ugv"])
@pytest.mark.parametrize("t0", [0.0, 30.0])
def test_noise_free_imu_integrates_to_the_true_trajectory(trajs, agent, t0):
    # Acceptance: integrating the noise-free IMU (200 Hz) from the true initial state reproduces the
    # true trajectory to < 0.1 % of the distance over 10 s. (Observed: micrometres.)
    tr = trajs[agent]
    imu = simulate_imu(tr, 200.0, ImuNoise().noise_free(), np.random.default_rng(0), duration=t0 + 10.0)
    m = imu.t >= t0 - 1e-9
    t = imu.t[m]
    assert t[-1] - t[0] == pytest.approx(10.0)
    T0 = tr.world_from_body(t[0])[0]
    R, p, v = integrate_imu(t, imu.gyro[m], imu.accel[m], T0[:3, :3], T0[:3, 3], tr.velocity(t[0])[0])
    dist = tr.path_length(t[-1]) - tr.path_length(t[0])
    assert dist > 0.5  # the first 10 s hold the take-off climb: metres, not tens
    err = np.linalg.norm(p - tr.position(t), axis=1).max()
    assert err < 1e-3 * dist
    assert np.abs(v - tr.velocity(t)).max() < 1e-3
    Rt = tr.rotation(t)
    ang = np.arccos(np.clip((np.einsum("nij,nij->n", R, Rt) - 1) / 2, -1, 1))
    assert ang.max() < 1e-5


def test_imu_at_rest_measures_gravity_and_zero_rate(trajs):
    tr = trajs["uav2"]
    imu = simulate_imu(tr, 200.0, ImuNoise().noise_free(), np.random.default_rng(0), duration=1.5)
    assert np.allclose(imu.accel, [0.0, 0.0, 9.81], atol=1e-9)  # specific force = -g in a z-up body
    assert np.allclose(imu.gyro, 0.0, atol=1e-12)


def test_imu_noise_matches_table2_discretisation(trajs):
    # White noise std = density * sqrt(rate); the bias walk grows with random_walk * sqrt(t).
    tr = trajs["ugv"]
    noise = ImuNoise()
    rate = 200.0
    clean = simulate_imu(tr, rate, noise.noise_free(), np.random.default_rng(1))
    noisy = simulate_imu(tr, rate, noise, np.random.default_rng(2))
    eg = noisy.gyro - clean.gyro - noisy.bias_gyro
    ea = noisy.accel - clean.accel - noisy.bias_accel
    n = eg.size
    tol = 4.0 / np.sqrt(2 * n)  # 4-sigma relative error of a sample std over n samples
    assert eg.std() == pytest.approx(noise.gyroscope_noise_density * np.sqrt(rate), rel=tol)
    assert ea.std() == pytest.approx(noise.accelerometer_noise_density * np.sqrt(rate), rel=tol)
    # bias random walk: increments over 1 s ~ random_walk * sqrt(1 s) (tau >> 1 s)
    k = int(rate)
    db = np.diff(noisy.bias_accel[::k], axis=0)
    assert db.std() == pytest.approx(noise.accelerometer_random_walk, rel=0.3)
    # gyro turn-on bias is constant and drawn with sigma 0.0087 rad/s: bounded by 5 sigma
    assert np.abs(noisy.bias_gyro[0]).max() < 5 * noise.gyroscope_turn_on_bias_sigma


def test_gnss_noise_matches_table3(trajs):
    tr = trajs["uav1"]
    g = simulate_gnss(tr, 5.0, GnssNoise(), np.random.default_rng(3))
    assert g.t[1] - g.t[0] == pytest.approx(0.2)
    e = g.enu - g.enu_true
    tol = 5.0 / np.sqrt(2 * len(e))
    assert e[:, :2].std() == pytest.approx(0.05, rel=tol)
    assert e[:, 2].std() == pytest.approx(0.15, rel=tol)


def test_nmea_round_trip_to_1mm(trajs):
    sc = get_scenario("factory01")
    origin = GeodeticOrigin(sc.origin_lat, sc.origin_lon, sc.origin_alt)
    g = simulate_gnss(trajs["uav3"], 5.0, GnssNoise(), np.random.default_rng(4))
    t_ns = sc.start_time_ns + np.round(g.t * 1e9).astype(np.int64)
    lla = enu_to_geodetic(g.enu, origin)
    sentences = [format_gpgga(int(t), *row) for t, row in zip(t_ns, lla, strict=True)]
    fixes = [parse_gpgga(s) for s in sentences]
    back = geodetic_to_enu(np.array([[f.lat, f.lon, f.alt] for f in fixes]), origin)
    assert np.abs(back - g.enu).max() < 1e-3
    # UTC time of day in the sentence matches the timestamp (10 ms resolution)
    tod = (t_ns % (86400 * 10**9)) / 1e9
    assert np.allclose([f.time_of_day_s for f in fixes], tod, atol=0.006)
    # Wuhan is north/east: the sentence says N and E
    assert ",N," in sentences[0] and ",E," in sentences[0]


def test_nmea_parser_rejects_corrupt_sentences():
    s = format_gpgga(1_700_000_000_000_000_000, 30.5, 114.3, 20.0)
    assert parse_gpgga(s).lat == pytest.approx(30.5, abs=1e-12)
    with pytest.raises(ValueError, match="checksum"):
        parse_gpgga(s.replace("30", "31", 1))
    with pytest.raises(ValueError):
        parse_gpgga("GPGGA,no dollar")
    # southern/western hemispheres
    f = parse_gpgga(format_gpgga(0, -33.8688, -151.2093, 5.0))
    assert (f.lat, f.lon) == (pytest.approx(-33.8688, abs=1e-10), pytest.approx(-151.2093, abs=1e-10))
