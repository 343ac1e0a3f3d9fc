"""Excitation datasets: alignment, envelopes, determinism, file round trip, bad input."""

import hashlib

import numpy as np
import pytest

from sim import NOMINAL, NoiseModel, Simulator
from sim.identification.excitation import REGIMES, load_dataset, make_dataset

TOL = {
    "noise_std": 0.05,   # sample std of the logged noise vs the stated std (50k samples per state)
    "realized_rounding": 1e-12,   # command vs realized wrench off saturation (N, and mN m for the torques)
}


def test_next_state_is_one_simulator_step_of_state_and_input(clean_small):
    ds = clean_small
    x_next = Simulator().step(ds.x.reshape(-1, 12), ds.u.reshape(-1, 4)).reshape(ds.x.shape)
    assert np.array_equal(x_next, ds.x_next)
    # Consecutive samples chain: x_next[k] is x[k + 1].
    assert np.array_equal(ds.x_next[:, :-1], ds.x[:, 1:])


def test_logged_input_is_the_one_applied_during_the_step(clean_small):
    # Pairing x_t with u_{t+1} (the public code's error) must not reproduce x_{t+1}.
    ds = clean_small
    shifted = Simulator().step(ds.x[:, :-1].reshape(-1, 12), ds.u[:, 1:].reshape(-1, 4))
    assert not np.allclose(shifted, ds.x_next[:, :-1].reshape(-1, 12), rtol=0, atol=1e-9)


def envelope(ds):
    ang = np.degrees(np.abs(ds.x[..., 3:5]))
    return ang[..., 0].max(), ang[..., 1].max()


def test_small_regime_reaches_15_and_never_exceeds_20_degrees(clean_small):
    roll, pitch = envelope(clean_small)
    assert 15.0 <= roll <= 20.0 and 15.0 <= pitch <= 20.0, (roll, pitch)
    assert clean_small.summary()["envelope_reached"]


def test_aggressive_regime_reaches_45_to_60_degrees(clean_aggressive):
    roll, pitch = envelope(clean_aggressive)
    assert 45.0 <= roll <= 60.0 and 45.0 <= pitch <= 60.0, (roll, pitch)
    assert clean_aggressive.summary()["envelope_reached"]


@pytest.mark.parametrize("regime", list(REGIMES))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_envelope_holds_for_other_seeds(regime, seed):
    ds = make_dataset(regime, 4, 10.0, 100 + seed, noise=NoiseModel.none())
    lo, hi = REGIMES[regime].envelope_deg
    roll, pitch = envelope(ds)
    assert max(roll, pitch) <= hi and min(roll, pitch) >= lo, (roll, pitch)


def file_hash(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_same_seed_gives_byte_identical_files_and_other_seeds_differ(tmp_path):
    paths = []
    for name, seed in (("a", 7), ("b", 7), ("c", 8)):
        paths.append(make_dataset("small", 3, 1.0, seed).save(tmp_path / f"{name}.npz"))
    assert file_hash(paths[0]) == file_hash(paths[1])
    assert file_hash(paths[0]) != file_hash(paths[2])
    a, c = load_dataset(paths[0]), load_dataset(paths[2])
    assert not np.allclose(a.x, c.x)


def test_trajectory_does_not_depend_on_dataset_size():
    few = make_dataset("small", 2, 2.0, 5)
    many = make_dataset("small", 5, 2.0, 5)
    assert np.array_equal(few.x, many.x[:2]) and np.array_equal(few.rotor_speed, many.rotor_speed[:2])


def test_save_load_round_trip(tmp_path):
    ds = make_dataset("aggressive", 3, 1.0, 1)
    back = load_dataset(ds.save(tmp_path / "d.npz"))
    for k in ds.ARRAYS:
        assert np.array_equal(getattr(ds, k), getattr(back, k)), k
    assert back.meta == ds.meta


def test_noise_is_the_stated_default():
    noisy = make_dataset("small", 5, 10.0, 2)
    clean = make_dataset("small", 5, 10.0, 2, noise=NoiseModel.none())
    err = (noisy.x - clean.x).reshape(-1, 12)
    np.testing.assert_allclose(err.std(axis=0), NoiseModel().state_std, rtol=TOL["noise_std"])
    n_err = (noisy.rotor_speed - clean.rotor_speed).ravel()
    np.testing.assert_allclose(n_err.std(), NoiseModel().rotor_speed, rtol=TOL["noise_std"])
    assert np.array_equal(noisy.u, clean.u)  # the flight itself does not see the noise


def test_split_is_by_trajectory():
    ds = make_dataset("small", 20, 0.5, 0)
    counts = np.bincount(ds.split, minlength=3)
    assert counts.tolist() == [14, 3, 3]
    pairs = ds.pairs("test")
    assert pairs["x"].shape == (3 * 50, 12)
    test_idx = np.flatnonzero(ds.split == 2)
    assert np.array_equal(pairs["x"][:50], ds.x[test_idx[0]])


@pytest.mark.parametrize("kwargs,arg", [
    (dict(regime="medium"), "regime"),
    (dict(duration=-1.0), "duration"),
    (dict(duration=float("nan")), "duration"),
    (dict(n_traj=0), "n_traj"),
    (dict(n_traj=2.5), "n_traj"),
    (dict(seed=-3), "seed"),
    (dict(noise="loud"), "noise"),
    (dict(workers=0), "workers"),
])
def test_bad_arguments_raise_value_error_naming_them(kwargs, arg):
    args = dict(regime="small", n_traj=2, duration=1.0, seed=0) | kwargs
    with pytest.raises(ValueError, match=arg):
        make_dataset(**args)


def test_load_rejects_foreign_files(tmp_path):
    f = tmp_path / "other.npz"
    np.savez(f, x=np.zeros(3))
    with pytest.raises(ValueError, match="missing"):
        load_dataset(f)
    with pytest.raises(ValueError, match="does not exist"):
        load_dataset(tmp_path / "nope.npz")


def test_the_noise_free_twin_is_the_same_flights_made_without_noise():
    noisy, clean = make_dataset("aggressive", 3, 2.0, 5, with_clean=True)
    assert noisy.fingerprint() == make_dataset("aggressive", 3, 2.0, 5).fingerprint()
    assert clean.fingerprint() == make_dataset("aggressive", 3, 2.0, 5, noise=NoiseModel.none()).fingerprint()


def test_realized_inputs_log_the_applied_wrench_of_the_same_flights():
    cmd = make_dataset("aggressive", 4, 5.0, 1)
    real = make_dataset("aggressive", 4, 5.0, 1, inputs="realized")
    assert np.array_equal(cmd.x, real.x) and np.array_equal(cmd.rotor_speed, real.rotor_speed)
    assert np.array_equal(real.u, cmd.wrench) and real.meta["inputs"] == "realized"
    # The command and the realized wrench differ where a rotor saturated, and only by rounding elsewhere.
    sat = np.any(cmd.saturated, axis=-1)
    gap = np.max(np.abs(cmd.u - real.u) / np.array([1.0, 1e-3, 1e-3, 1e-3]), axis=-1)
    assert sat.any() and np.all(gap[~sat] < TOL["realized_rounding"]) and np.all(gap[sat] > 1e3 * TOL["realized_rounding"])


# ------------------------------------------------------------------ the excitation at the ctbr level
#: The wrench level's dataset of ("small", 6 flights, 10 s, seed 0) before the excitation learned the ctbr level: its
#: arrays must not move.
WRENCH_FINGERPRINT = "930f0e93909c1a8f9f7e5cabe6ac31f67a2cfa179329db426ad915d5cc08cd69"


def _replayed(ds, plant: str, high_fidelity: bool = False):
    """Each noise-free trajectory flown again through a fresh plant at ctbr from its first state with its logged
    commands: the states (n_traj, n_steps, 12)."""
    from sim.plants.named import make_plant

    out = np.empty_like(ds.x_next)
    for i in range(ds.n_traj):
        pl = make_plant(plant, ds.meta["vehicle"], high_fidelity=high_fidelity, level="ctbr")
        pl.reset(ds.x[i, 0])
        for k in range(ds.x.shape[1]):
            out[i, k] = pl.step(ds.u[i, k]).x
    return out


def test_the_wrench_excitation_is_unchanged_by_the_levels():
    ds = make_dataset("small", 6, 10.0, 0)
    assert ds.fingerprint() == WRENCH_FINGERPRINT and "level" not in ds.meta and ds.level == "wrench"


@pytest.mark.parametrize("high_fidelity", [False, True])
def test_a_ctbr_excitation_logs_the_thrust_and_rate_commands_its_inner_loop_flew(high_fidelity):
    """Replayed through the vehicle's inner loop (a fresh plant at ctbr), the logged commands give the logged next
    states exactly; the rates stay inside the vehicle's largest rate command."""
    from sim.vehicles.vehicle import load_vehicle

    veh = load_vehicle(None)
    fidelity = veh.fidelity if high_fidelity else NOMINAL
    ds = make_dataset("aggressive", 3, 1.5, 4, noise=NoiseModel.none(), level="ctbr", fidelity=fidelity)
    assert ds.level == "ctbr" and ds.meta["level"] == "ctbr"
    assert np.array_equal(_replayed(ds, "sim", high_fidelity), ds.x_next)
    assert np.max(np.abs(ds.u[..., 1:])) <= veh.inner_loop_at("ctbr").max_rate
    # The wrench level's plant given the same numbers flies another flight.
    shifted = Simulator(veh.params, fidelity).step(ds.x[:, 0], ds.u[:, 0])
    assert not np.allclose(shifted, ds.x_next[:, 0], rtol=0, atol=1e-6)


def test_a_ctbr_excitation_on_rotorpy_replays_through_its_onboard_controller_and_any_worker_count():
    pytest.importorskip("rotorpy")
    one = make_dataset("small", 3, 0.5, 2, noise=NoiseModel.none(), level="ctbr", plant="rotorpy")
    two = make_dataset("small", 3, 0.5, 2, noise=NoiseModel.none(), level="ctbr", plant="rotorpy", workers=2)
    assert one.fingerprint() == two.fingerprint()
    assert np.array_equal(_replayed(one, "rotorpy"), one.x_next)


@pytest.mark.parametrize("regime", list(REGIMES))
def test_a_ctbr_excitation_reaches_its_regimes_envelope(regime):
    ds = make_dataset(regime, 4, 10.0, 100, noise=NoiseModel.none(), level="ctbr")
    lo, hi = REGIMES[regime].envelope_deg
    roll, pitch = envelope(ds)
    assert max(roll, pitch) <= hi and min(roll, pitch) >= lo, (roll, pitch)
    # Two ctbr datasets of one seed are equal; of sizes 2 and 4 share their first two flights.
    small = make_dataset(regime, 2, 10.0, 100, noise=NoiseModel.none(), level="ctbr")
    assert np.array_equal(small.x, ds.x[:2]) and np.array_equal(small.u, ds.u[:2])


@pytest.mark.parametrize("kwargs,match", [
    (dict(level="ctatt"), "level must be one of wrench, ctbr for an excitation"),
    (dict(level="torque"), "level must be one of wrench, ctbr, ctatt"),
    (dict(level="ctbr", inputs="realized"), "inputs='realized' logs a realized wrench"),
])
def test_bad_levels_are_refused_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_dataset("small", 2, 1.0, 0, **kwargs)


def test_data_at_ctbr_refuses_a_vehicle_without_an_inner_loop_and_writes_nothing(tmp_path, capsys):
    from scenarios.cli import main
    from sim.vehicles.vehicle import load_vehicle

    path = tmp_path / "bare.toml"
    path.write_text(load_vehicle("crazyflie").replace(name="bare", inner_loop=None).to_toml())
    out = tmp_path / "d.npz"
    assert main(["data", "--regime", "small", "--n-traj", "2", "--duration", "1", "--level", "ctbr",
                 "--vehicle", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "inner_loop.rate_kp is missing" in err and err.count("\n") == 1 and not out.exists(), err


@pytest.mark.parametrize("level", ["wrench", "ctbr"])
def test_data_and_train_refuse_an_output_they_cannot_write_before_any_work(tmp_path, capsys, level):
    """Under a file (no folder can be made there): one line naming --out, exit 2, nothing flown or trained."""
    from scenarios.cli import main

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main(["data", "--regime", "small", "--n-traj", "2", "--duration", "1", "--level", level,
                 "--out", str(blocker / "d.npz")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "cannot be written" in err and err.count("\n") == 1, err
    data = tmp_path / "d.npz"
    make_dataset("small", 8, 1.0, 0, level=level).save(data)
    arch = "ctbr" if level == "ctbr" else "baseline"
    assert main(["train", "--arch", arch, "--data", str(data), "--out", str(blocker / "models")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "cannot be written" in err and err.count("\n") == 1, err
    assert main(["train", "--arch", arch, "--data", str(data), "--out", str(blocker)]) == 2
    err = capsys.readouterr().err
    assert "is a file; give a folder" in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "d.npz"]
