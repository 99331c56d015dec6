"""Known-answer tests of the outdoor propagation model."""

import numpy as np
import pytest
import scipy.fft as sfft

from acoustlab.core.types import NoiseRegime, Site
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.propagation import (
    cylinder_scattering_table,
    ground_impedance,
    spherical_reflection_coefficient,
)
from plugins.simulators.outdoor import OutdoorSimulator, band_weights

FS = 48000.0
N_FFT = 2**15


def make_site(mics, trees=np.zeros((0, 2)), diameters=np.zeros(0), model="rigid", sigma=2e4, layer=None, snr=(200, 200)):
    return Site(
        name="test",
        mic_positions_m=np.asarray(mics, float),
        tree_positions_m=np.asarray(trees, float),
        trunk_diameters_m=np.asarray(diameters, float),
        temperature_range_c=(20.0, 20.0),
        relative_humidity_range_pct=(50.0, 50.0),
        ground_type="test",
        ground_flow_resistivity_kpa_s_m2=sigma,
        ground_impedance_model=model,
        ground_layer_thickness_m=layer,
        noise_regimes=(NoiseRegime("white"),),
        snr_range_db=snr,
        species_pool=("synthetic",),
        source_height_range_m=(1.5, 1.5),
        hull_expansion=0.1,
    )


MICS = [[0.0, 0.0, 1.5], [40.0, 0.0, 1.5], [20.0, 35.0, 1.5]]
FREQS = sfft.rfftfreq(N_FFT, 1 / FS)


def impulse_response(h):
    return sfft.irfft(h, n=N_FFT, axis=-1)


def test_direct_path_arrives_at_distance_over_c():
    sim = OutdoorSimulator(sample_rate_hz=FS, ground=False, air_absorption=False)
    site = make_site(MICS)
    src = np.array([12.3, 7.9, 1.5])
    h = sim.transfer_functions(site, src, 20.0, 50.0, FREQS, N_FFT)
    c = speed_of_sound_m_s(20.0, 50.0)
    dist = np.linalg.norm(np.asarray(MICS) - src, axis=1)
    peaks = np.argmax(np.abs(impulse_response(h["direct"])), axis=1)
    np.testing.assert_allclose(peaks, dist / c * FS, atol=1.0)
    # amplitude spreads as 1/r
    np.testing.assert_allclose(np.abs(h["direct"][:, 1]), 1 / dist, rtol=1e-9)


def test_rigid_ground_reflection_at_image_distance_and_first_dip():
    sim = OutdoorSimulator(sample_rate_hz=FS, air_absorption=False, trunks={"enabled": False})
    site = make_site([[0, 0, 1.5], [30, 0, 1.5], [0, 30, 1.5]], model="rigid")
    src = np.array([20.0, 0.0, 2.0])
    h = sim.transfer_functions(site, src, 20.0, 50.0, FREQS, N_FFT)
    c = speed_of_sound_m_s(20.0, 50.0)
    mic = np.array([0.0, 0.0, 1.5])
    r1 = np.linalg.norm(mic - src)
    r2 = np.linalg.norm(mic - src * [1, 1, -1])
    ir = impulse_response(h["ground"][0])
    assert np.argmax(np.abs(ir)) == pytest.approx(r2 / c * FS, abs=1.0)
    total = np.abs(h["direct"][0] + h["ground"][0])
    f_dip = c / (2 * (r2 - r1))
    band = (0.5 * f_dip < FREQS) & (1.5 * f_dip > FREQS)
    assert FREQS[band][np.argmin(total[band])] == pytest.approx(f_dip, rel=0.02)


def test_soft_ground_at_grazing_does_not_cancel_the_direct_sound():
    # 200 m over grass (σ = 200 kPa·s·m⁻²), source and mic at 0.5 m, low frequencies: the
    # classical case where the plane-wave coefficient (R_p ≈ −1) predicts a deep cancellation
    f = np.array([125.0, 250.0])
    r1, hs, hr = 200.0, 0.5, 0.5
    r2 = np.sqrt(r1**2 + (hs + hr) ** 2)
    z = ground_impedance(f, 200.0, "delany_bazley")
    q = spherical_reflection_coefficient(f, z, np.array(r2), np.array((hs + hr) / r2), 343.0)
    k = 2 * np.pi * f / 343.0
    total = np.abs(1 + q * (r1 / r2) * np.exp(1j * k * (r2 - r1)))
    rp = (z * (hs + hr) / r2 - 1) / (z * (hs + hr) / r2 + 1)
    plane = np.abs(1 + rp * (r1 / r2) * np.exp(1j * k * (r2 - r1)))
    assert (total > 0.5).all(), "the ground wave must keep the field from cancelling"
    assert (total > 3 * plane).all(), "plane-wave theory predicts near-total cancellation"


def test_rigid_ground_gives_q_equal_one():
    f = np.array([500.0, 4000.0])
    q = spherical_reflection_coefficient(f, ground_impedance(f, 1.0, "rigid"), np.array(10.0), np.array(0.2), 343.0)
    np.testing.assert_allclose(q, 1.0, atol=1e-6)


def test_scattered_arrival_at_d1_plus_d2_over_c():
    tree = np.array([[15.0, 12.0]])
    sim = OutdoorSimulator(sample_rate_hz=FS, ground=False, air_absorption=False, occlusion=False)
    site = make_site(MICS, tree, [0.4])
    src = np.array([5.0, 5.0, 1.5])
    h = sim.transfer_functions(site, src, 20.0, 50.0, FREQS, N_FFT)
    c = speed_of_sound_m_s(20.0, 50.0)
    d1 = np.linalg.norm(tree[0] - src[:2])
    d2 = np.linalg.norm(tree[0] - np.asarray(MICS)[:, :2], axis=1)
    ir = impulse_response(h["trunks"])
    np.testing.assert_allclose(np.argmax(np.abs(ir), axis=1), (d1 + d2) / c * FS, atol=1.5)
    assert (np.abs(ir).max(axis=1) < np.abs(impulse_response(h["direct"])).max(axis=1)).all()


def test_trunk_in_front_of_the_mic_shadows_high_frequencies():
    sim = OutdoorSimulator(sample_rate_hz=FS, ground=False, air_absorption=False, trunks={"enabled": False})
    src = np.array([20.0, 0.3, 1.5])
    clear = sim.transfer_functions(make_site(MICS), src, 20.0, 50.0, FREQS, N_FFT)
    blocked = sim.transfer_functions(make_site(MICS, [[0.8, 0.0]], [0.5]), src, 20.0, 50.0, FREQS, N_FFT)
    ratio_db = 20 * np.log10(np.abs(blocked["direct"][0]) / np.abs(clear["direct"][0]))
    assert ratio_db[np.searchsorted(FREQS, 4000)] < -6
    assert ratio_db[np.searchsorted(FREQS, 4000)] < ratio_db[np.searchsorted(FREQS, 250)]
    assert blocked["delay_direct_s"][0] > clear["delay_direct_s"][0]
    np.testing.assert_allclose(blocked["direct"][1:], clear["direct"][1:])


def test_cylinder_series_rayleigh_limit_and_band_partition():
    ka, _, table = cylinder_scattering_table()
    small = ka < 0.05
    slope = np.polyfit(np.log(ka[small]), np.log(np.abs(table[small, 90])), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.1)  # |A| ∝ (ka)² in the Rayleigh regime
    w = band_weights(FREQS[1:], np.array([250, 500, 1000, 2000, 4000, 8000.0]))
    np.testing.assert_allclose(w.sum(axis=0), 1.0, atol=1e-12)


def test_temperature_shifts_tdoas_as_geometry_predicts():
    sim = OutdoorSimulator(sample_rate_hz=FS, ground=False, air_absorption=False)
    site = make_site(MICS)
    src = np.array([30.0, 20.0, 1.5])
    cold = sim.transfer_functions(site, src, -15.0, 80.0, FREQS, N_FFT)["delay_direct_s"]
    warm = sim.transfer_functions(site, src, 15.0, 80.0, FREQS, N_FFT)["delay_direct_s"]
    ratio = speed_of_sound_m_s(15.0, 80.0) / speed_of_sound_m_s(-15.0, 80.0)
    np.testing.assert_allclose((cold - cold[0])[1:], ((warm - warm[0]) * ratio)[1:], rtol=1e-9)


def test_realised_snr_and_same_seed_same_audio():
    site = make_site(MICS, snr=(12.0, 12.0))
    sim = OutdoorSimulator(sample_rate_hz=24000.0, air_absorption=False)
    ids = np.arange(6)
    noisy = sim.simulate(site, ids, ids, seed=5)
    again = sim.simulate(site, ids, ids, seed=5)
    np.testing.assert_array_equal(noisy.audio, again.audio)
    clean = sim.simulate(make_site(MICS, snr=(300.0, 300.0)), ids, ids, seed=5)
    noise = noisy.audio.astype(float) - clean.audio.astype(float)
    dist = np.linalg.norm(clean.true_position_m[:, None, :] - np.asarray(MICS)[None], axis=2)
    nearest = np.argmin(dist, axis=1)
    n = np.arange(6)
    dur = noisy.events["call_duration_s"].to_numpy() * 24000.0
    snr = 10 * np.log10((clean.audio[n, nearest].astype(float) ** 2).sum(-1) / dur / noise[n, nearest].var(-1))
    np.testing.assert_allclose(snr, 12.0, atol=0.5)


def test_impairments_are_recorded_and_applied():
    site = make_site(MICS, snr=(30.0, 30.0))
    sim = OutdoorSimulator(sample_rate_hz=24000.0, impairments={"interference_probability": 1.0, "failure_probability": 1.0})
    batch = sim.simulate(site, np.arange(8), np.arange(8), seed=0)
    assert (batch.events["interference_mic"] >= 0).all() and (batch.events["failed_mic"] >= 0).all()
    dead = batch.events.index[batch.events["failure_mode"] == "dead"]
    for e in dead:
        mic = batch.events.loc[e, "failed_mic"]
        assert np.abs(batch.audio[e, mic]).max() < 0.01 * np.abs(batch.audio[e]).max()


def test_both_scattering_renderers_agree(monkeypatch):
    import plugins.simulators.outdoor as outdoor

    rng = np.random.default_rng(3)
    trees = rng.uniform(-20, 60, size=(40, 2))
    site = make_site(MICS, trees, rng.uniform(0.1, 0.6, 40))
    sim = OutdoorSimulator(sample_rate_hz=FS, ground=False)
    src = np.array([18.0, 11.0, 1.5])
    monkeypatch.setattr(outdoor, "_KERNEL_COST_FACTOR", 1e9)
    kernels = sim.transfer_functions(site, src, 10.0, 60.0, FREQS, N_FFT)["trunks"]
    monkeypatch.setattr(outdoor, "_KERNEL_COST_FACTOR", 0.0)
    bands = sim.transfer_functions(site, src, 10.0, 60.0, FREQS, N_FFT)["trunks"]
    a, b = impulse_response(kernels), impulse_response(bands)
    assert np.abs(a).max() > 0
    # same arrivals; the band shaping differs only by the kernels' finite frequency resolution
    assert np.abs(a - b).max() < 0.1 * np.abs(a).max()
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.98
