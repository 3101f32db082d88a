"""The analytic Euler–Lagrange baseline: its regressor against MuJoCo's own inverse dynamics of the fixed-base legs,
identification on MuJoCo-generated data, positive definiteness and the shared model interface."""

from types import SimpleNamespace

import mujoco
import numpy as np
import pytest
import torch

from training.dynamics.analytic import (
    AnalyticConfig,
    AnalyticModel,
    ChainTensors,
    identify,
    identify_dataset,
    make_tree,
    nominal_parameters,
    read_chain,
    regressor,
    resolve_mjcf,
)

CONFIG = AnalyticConfig()
COULOMB = 0.05  # N m, added to the synthetic data through qfrc_applied (the MJCF has no tanh friction)


@pytest.fixture(scope="module")
def fixed_base():
    """BRUCE with the pelvis welded to the world: free joint and keyframe removed, no contacts or constraints,
    plain semi-implicit Euler (implicit damping off), so MuJoCo's step is exactly the model's update."""
    spec = mujoco.MjSpec.from_file(str(resolve_mjcf(CONFIG.mjcf)))
    spec.delete(spec.body(CONFIG.base_body).joints[0])
    for key in list(spec.keys):
        spec.delete(key)
    off = mujoco.mjtDisableBit
    spec.option.disableflags |= off.mjDSBL_CONTACT | off.mjDSBL_CONSTRAINT | off.mjDSBL_EULERDAMP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    model = spec.compile()
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)]
    assert names == list(CONFIG.joints)  # qpos/qvel are then in the config's joint order
    return model


@pytest.fixture(scope="module")
def chain_tensors():
    chain = read_chain(CONFIG)
    kin = ChainTensors(*(torch.as_tensor(x, dtype=torch.float64)
                         for x in (chain.body_pos, chain.body_rot, chain.axis, chain.gravity)))
    return chain, kin, make_tree(chain.parent)


def random_states(chain, rng, batch):
    q = rng.uniform(chain.q_lower, chain.q_upper, (batch, CONFIG.n_joints))
    return q, rng.normal(0.0, 3.0, q.shape), rng.normal(0.0, 50.0, q.shape)


def simulate(model, seconds, seed):
    """A fixed-base rollout under a PD on random sinusoidal targets plus noise, Coulomb friction added as
    -COULOMB tanh(qd / v_c). Returns q, qd [T + 1, n] and the recorded torque tau [T, n] (tau[t] over t -> t+1)."""
    rng = np.random.default_rng(seed)
    chain = read_chain(CONFIG)
    mid, half = (chain.q_lower + chain.q_upper) / 2, (chain.q_upper - chain.q_lower) / 2
    freq, phase = rng.uniform(0.3, 3.0, (3, 10)), rng.uniform(0, 2 * np.pi, (3, 10))
    amp = rng.uniform(0.1, 0.3, (3, 10))
    data = mujoco.MjData(model)
    data.qpos[:] = mid + rng.uniform(-0.2, 0.2, 10) * half
    steps = round(seconds / model.opt.timestep)
    q, qd, tau = np.zeros((steps + 1, 10)), np.zeros((steps + 1, 10)), np.zeros((steps, 10))
    for t in range(steps + 1):
        q[t], qd[t] = data.qpos, data.qvel
        if t == steps:
            break
        target = mid + half * np.clip((amp * np.sin(2 * np.pi * freq * t * 1e-3 + phase)).sum(0), -0.8, 0.8)
        tau[t] = 2.0 * (target - data.qpos) - 0.1 * data.qvel + rng.normal(0.0, 0.2, 10)
        data.qfrc_applied[:] = tau[t] - COULOMB * np.tanh(data.qvel / CONFIG.coulomb_velocity)
        mujoco.mj_step(model, data)
    return q, qd, tau


@pytest.fixture(scope="module")
def rollout(fixed_base):
    return simulate(fixed_base, 1.5, seed=1)


def as64(*arrays):
    return tuple(torch.as_tensor(a, dtype=torch.float64) for a in arrays)


# -- the regressor is the rigid-body dynamics -------------------------------------------------------------------
def test_regressor_with_the_mjcf_parameters_is_mujoco_inverse_dynamics(fixed_base, chain_tensors):
    chain, kin, tree = chain_tensors
    q, qd, qdd = random_states(chain, np.random.default_rng(0), 32)
    data = mujoco.MjData(fixed_base)
    expected = np.zeros_like(q)
    for b in range(len(q)):
        data.qpos[:], data.qvel[:], data.qacc[:] = q[b], qd[b], qdd[b]
        mujoco.mj_inverse(fixed_base, data)  # M qacc + bias - passive (armature and damping included)
        expected[b] = data.qfrc_inverse
    pi_true = nominal_parameters(CONFIG)
    y = regressor(kin, tree, *as64(q, qd, qdd), CONFIG.coulomb_velocity).numpy()

    assert y.shape == (32, CONFIG.n_joints, CONFIG.n_params) == (32, 10, 130)
    assert np.abs(expected).max() > 1.0  # the comparison is not between near-zeros
    np.testing.assert_allclose(y @ pi_true, expected, rtol=0, atol=1e-9)
    # The module's own RNEA on the parameters (how forward evaluates M and h) agrees with the regressor.
    model = AnalyticModel(CONFIG, dtype=torch.float64)
    np.testing.assert_allclose(model.inverse_dynamics(*as64(q, qd, qdd)).numpy(), expected, rtol=0, atol=1e-9)
    assert len(CONFIG.param_names()) == CONFIG.n_params


def test_mass_matrix_is_mujocos_and_positive_definite(fixed_base, chain_tensors):
    chain = chain_tensors[0]
    q = random_states(chain, np.random.default_rng(1), 16)[0]
    data = mujoco.MjData(fixed_base)
    expected = np.zeros((len(q), 10, 10))
    for b in range(len(q)):
        data.qpos[:] = q[b]
        mujoco.mj_forward(fixed_base, data)
        mujoco.mj_fullM(fixed_base, data, expected[b])
    mass = AnalyticModel(CONFIG, dtype=torch.float64).mass_matrix(*as64(q)).numpy()
    np.testing.assert_allclose(mass, expected, rtol=0, atol=1e-12)

    mass32 = AnalyticModel(CONFIG).mass_matrix(torch.as_tensor(q, dtype=torch.float32))
    assert mass32.dtype == torch.float32
    assert torch.equal(mass32, mass32.transpose(1, 2))
    assert torch.linalg.eigvalsh(mass32.double()).min() > 1e-3  # >= the 0.0018 armature, to rounding
    assert np.abs(mass[:, :5, 5:]).max() == 0  # a fixed base decouples the legs


# -- identification -----------------------------------------------------------------------------------------------
def test_identification_on_mujoco_data_recovers_torques_friction_and_next_state(rollout, chain_tensors):
    chain, kin, tree = chain_tensors
    q, qd, tau = rollout
    n_fit = 1200
    model = identify(q[:n_fit], qd[:n_fit], tau[:n_fit], CONFIG.dt, config=CONFIG, dtype=torch.float64)
    report = model.identification

    pi = model.params.numpy()
    qdd = (qd[1:n_fit] - qd[:n_fit - 1]) / CONFIG.dt
    y = regressor(kin, tree, *as64(q[:n_fit - 1], qd[:n_fit - 1], qdd), CONFIG.coulomb_velocity).numpy()
    assert np.abs(y @ pi - tau[:n_fit - 1]).max() < 1e-9 * np.abs(tau).max()
    assert max(report.relative_residual.values()) < 1e-9
    assert report.n_samples == n_fit - 1 and report.armature_shift == 0.0
    assert all(13 * 5 > rank > 30 for rank in report.rank.values())  # base parameters: fewer than 65 per leg
    # Friction columns are identifiable one by one: damping 0.01 from the MJCF, Coulomb from the applied torque.
    n = CONFIG.n_joints
    np.testing.assert_allclose(pi[11 * n:12 * n], 0.01, atol=1e-7)
    np.testing.assert_allclose(pi[12 * n:], COULOMB, atol=1e-7)

    # One step on the held-out tail: MuJoCo's next state, to float64 rounding.
    tail = slice(n_fit, len(tau))
    with torch.no_grad():
        q_next, qd_next = model(*as64(q[tail], qd[tail], tau[tail]))
    increment = np.abs(qd[1:][tail] - qd[tail]).max()
    assert np.abs(qd_next.numpy() - qd[1:][tail]).max() < 1e-8 * increment
    assert np.abs(q_next.numpy() - q[1:][tail]).max() < 1e-12

    # The default float32 model: the same prediction to float32 rounding.
    model32 = identify(q[:n_fit], qd[:n_fit], tau[:n_fit], CONFIG.dt, config=CONFIG)
    assert model32.params.dtype == torch.float32
    with torch.no_grad():
        q32, qd32 = model32(*(torch.as_tensor(a, dtype=torch.float32) for a in (q[tail], qd[tail], tau[tail])))
    assert np.abs(qd32.numpy() - qd[1:][tail]).max() < 1e-4 * increment
    assert np.abs(q32.numpy() - q[1:][tail]).max() < 1e-6


def test_transitions_across_an_episode_boundary_are_not_fitted(fixed_base, rollout):
    """Two recordings spliced end to end: with the episode marks the fit stays exact, without them the splice's
    fake acceleration pollutes it."""
    q1, qd1, tau1 = rollout
    q2, qd2, tau2 = simulate(fixed_base, 0.6, seed=7)
    q = np.vstack([q1[:-1], q2[:-1]])
    qd = np.vstack([qd1[:-1], qd2[:-1]])
    tau = np.vstack([tau1, tau2])
    episode = np.repeat([0, 1], [len(tau1), len(tau2)])

    marked_model = identify(q, qd, tau, CONFIG.dt, episode, config=CONFIG, dtype=torch.float64)
    marked = marked_model.identification
    spliced = identify(q, qd, tau, CONFIG.dt, config=CONFIG, dtype=torch.float64).identification
    assert marked.n_samples == len(q) - 2 and spliced.n_samples == len(q) - 1
    assert max(marked.relative_residual.values()) < 1e-9
    assert max(spliced.relative_residual.values()) > 1e-4
    # The same through a Dataset-like split (training.dataset.Dataset has these attributes).
    split = SimpleNamespace(q=q, qd=qd, tau=tau, dt=CONFIG.dt, episode=episode)
    via_split = identify_dataset(split, CONFIG, dtype=torch.float64)
    torch.testing.assert_close(via_split.params, marked_model.params, rtol=0, atol=0)


def test_an_indefinite_mass_matrix_gets_an_armature_floor(chain_tensors):
    """Torques generated by parameters with negative armature: the least-squares fit reproduces them, so M(q) is
    indefinite, and identify raises every armature until lambda_min(M) reaches the configured floor."""
    chain, kin, tree = chain_tensors
    rng = np.random.default_rng(3)
    steps = 800
    t = np.arange(steps + 1)[:, None] * CONFIG.dt
    q = (chain.q_lower + chain.q_upper) / 2 + 0.4 * np.sin(2 * np.pi * rng.uniform(0.5, 4, 10) * t
                                                            + rng.uniform(0, 6, 10))
    qd = np.gradient(q, CONFIG.dt, axis=0) + rng.normal(0, 0.5, q.shape)  # any qd: the fit only needs tau = Y pi
    bad = nominal_parameters(CONFIG)
    bad[10 * 10:11 * 10] = -0.01  # armature
    qdd = (qd[1:] - qd[:-1]) / CONFIG.dt
    tau = regressor(kin, tree, *as64(q[:-1], qd[:-1], qdd), CONFIG.coulomb_velocity).numpy() @ bad

    plain = AnalyticModel(CONFIG, bad, dtype=torch.float64)
    assert torch.linalg.eigvalsh(plain.mass_matrix(*as64(q[:-1]))).min() < 0  # the premise

    floor = 2e-3
    config = AnalyticConfig(min_mass_eigenvalue=floor)
    model = identify(q[:-1], qd[:-1], tau, CONFIG.dt, config=config, dtype=torch.float64)
    report = model.identification
    assert report.armature_shift > 0
    assert report.min_mass_eigenvalue == pytest.approx(floor)
    states = np.vstack([q, rng.uniform(chain.q_lower, chain.q_upper, (256, 10))])
    assert torch.linalg.eigvalsh(model.mass_matrix(*as64(states))).min() > floor * 0.99


# -- the shared model interface ------------------------------------------------------------------------------------
def test_forward_has_the_shared_interface_and_is_semi_implicit_euler(rollout):
    q, qd, tau = rollout
    model = identify(q[:1000], qd[:1000], tau[:1000], CONFIG.dt, config=CONFIG)
    assert model.n_joints == 10 and model.dt == CONFIG.dt
    assert model.initial_state() == () and model.initial_state(batch=4) == ()

    batch = [torch.as_tensor(a[100:104], dtype=torch.float32) for a in (q, qd, tau)]
    out = model(*batch, *model.initial_state(4))
    assert len(out) == 2 and all(o.shape == (4, 10) and o.dtype == torch.float32 for o in out)
    q_next, qd_next = out
    qdd = model.acceleration(*batch)
    torch.testing.assert_close(qd_next, batch[1] + qdd * model.dt)
    torch.testing.assert_close(q_next, batch[0] + qd_next * model.dt)  # the new velocity, as MuJoCo does

    model.fit_normalisation(SimpleNamespace(q_std=np.ones(10)))  # nothing to fit, but the joints must match
    with pytest.raises(ValueError, match=r"q_std has shape \(7,\)"):
        model.fit_normalisation(SimpleNamespace(q_std=np.ones(7)))

    # A checkpoint restores the identified model into a freshly built one (kinematics and parameters are buffers).
    fresh = AnalyticModel(CONFIG)
    assert not torch.equal(fresh(*batch)[1], qd_next)
    fresh.load_state_dict(model.state_dict())
    torch.testing.assert_close(fresh(*batch)[1], qd_next, rtol=0, atol=0)


def test_bad_inputs_fail_naming_the_problem(rollout):
    q, qd, tau = rollout
    with pytest.raises(ValueError, match=r"tau has shape \[1500, 9\], expected \[1501, 10\]"):
        identify(q, qd, tau[:, :9], CONFIG.dt, config=CONFIG)
    with pytest.raises(ValueError, match="dt = 0.002 s does not match"):
        identify(q, qd, np.vstack([tau, tau[-1:]]), 0.002, config=CONFIG)
    with pytest.raises(ValueError, match="episode has shape"):
        identify(q[:-1], qd[:-1], tau, CONFIG.dt, np.zeros(3), config=CONFIG)
    with pytest.raises(ValueError, match="no joint named 'r_elbow'"):
        AnalyticModel(AnalyticConfig(joints=("r_elbow",)))
    with pytest.raises(ValueError, match=r"params must have shape \(130,\)"):
        AnalyticModel(CONFIG, np.zeros(12))
