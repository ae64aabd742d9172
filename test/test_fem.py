"""Tests of core/physics/fem.py: K0 against scikit-fem, corotational invariance, Neo-Hookean Hessian and
forces against torch autograd, SPD projection and the definiteness check."""

from itertools import permutations
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import torch

from meshfg_ros.core.physics import fem
from meshfg_ros.core.physics.fem import (
    DegenerateElementError,
    ElasticModel,
    InvalidMaterialError,
    InvalidStateError,
    UnknownStiffnessKindError,
    definiteness,
    free_dofs,
    is_indefinite,
    polar_rotations,
)

LIVER_PATH = Path("/work/shared/data/liver.msh")
YOUNGS_MODULUS = 3000.0  # Pa, soft tissue
POISSON_RATIO = 0.45


def structured_cube(cells: int, side: float = 1.0):
    """(vertices, tetrahedra) of a cube split into cells^3 sub-cubes of 6 Kuhn tetrahedra each."""
    axis = np.linspace(0.0, side, cells + 1)
    vertices = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    corner = np.stack(np.meshgrid(*[np.arange(cells)] * 3, indexing="ij"), axis=-1).reshape(-1, 1, 3)
    tet_offsets = []
    for order in permutations(range(3)):
        path = [np.zeros(3, dtype=np.int64)]
        for axis_index in order:
            step = path[-1].copy()
            step[axis_index] = 1
            path.append(step)
        tet_offsets.append(path)
    grid = corner[:, None, :, :] + np.array(tet_offsets)[None]  # (cubes, 6, 4, 3)
    flat = (grid[..., 0] * (cells + 1) + grid[..., 1]) * (cells + 1) + grid[..., 2]
    return vertices, flat.reshape(-1, 4).astype(np.int64)


def relative_difference(a, b) -> float:
    a = a.toarray() if hasattr(a, "toarray") else np.asarray(a)
    b = b.toarray() if hasattr(b, "toarray") else np.asarray(b)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def rotation_matrix(axis, angle) -> np.ndarray:
    return scipy.linalg.expm(angle * np.cross(np.eye(3), np.asarray(axis, float) / np.linalg.norm(axis)))


@pytest.fixture(scope="module")
def cube_model():
    vertices, tets = structured_cube(3, side=0.05)
    return ElasticModel(vertices, tets, YOUNGS_MODULUS, POISSON_RATIO)


@pytest.fixture(scope="module")
def liver_arrays():
    from meshfg_ros.core.geometry.mesh import load_mesh

    mesh = load_mesh(LIVER_PATH)
    return np.asarray(mesh.vertices), np.asarray(mesh.tetrahedra)


def bottom_vertices(vertices) -> np.ndarray:
    return np.flatnonzero(np.isclose(vertices[:, 2], vertices[:, 2].min()))


def compressed_sheared_state(model, compression=0.35, stretch=1.3, shear=0.6):
    """Bottom kept; height scaled from `stretch` (at min x) to `compression` (at max x), sheared in x.

    Elements near min x are in tension (PSD Neo-Hookean Hessians), those near max x strongly
    compressed (indefinite ones).
    """
    rest = model.rest_vertices
    height = rest[:, 2] - rest[:, 2].min()
    along_x = (rest[:, 0] - rest[:, 0].min()) / np.ptp(rest[:, 0])
    state = rest.copy()
    state[:, 2] = rest[:, 2].min() + (stretch + (compression - stretch) * along_x) * height
    state[:, 0] += shear * height
    return state


# ------------------------------------------------------------------------------ linear K0


def skfem_stiffness(vertices, tets):
    """scikit-fem's linear-elasticity K with its dofs permuted to our x0 y0 z0 x1 ... order."""
    from skfem import Basis, ElementTetP1, ElementVector, MeshTet, asm
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    basis = Basis(MeshTet(vertices.T.copy(), tets.T.copy()), ElementVector(ElementTetP1()))
    stiffness = asm(linear_elasticity(*lame_parameters(YOUNGS_MODULUS, POISSON_RATIO)), basis)
    # nodal_dofs[c, v] is skfem's dof of component c at vertex v; ours is 3 v + c.
    ours_of_skfem = np.empty(stiffness.shape[0], dtype=np.int64)
    ours_of_skfem[basis.nodal_dofs.T.reshape(-1)] = np.arange(stiffness.shape[0])
    permutation = np.argsort(ours_of_skfem)  # our dof d sits at skfem index permutation[d]
    return stiffness[permutation][:, permutation]


def test_linear_stiffness_matches_scikit_fem_on_cube(cube_model):
    reference = skfem_stiffness(cube_model.rest_vertices, cube_model.tetrahedra)
    assert relative_difference(cube_model.stiffness(kind="linear"), reference) < 1e-9


def test_linear_stiffness_matches_scikit_fem_on_liver(liver_arrays):
    vertices, tets = liver_arrays
    model = ElasticModel(vertices, tets, YOUNGS_MODULUS, POISSON_RATIO)
    assert relative_difference(model.stiffness(kind="linear"), skfem_stiffness(vertices, tets)) < 1e-9


@pytest.mark.parametrize("poisson_ratio", [0.0, 0.3, 0.49])
def test_linear_stiffness_parts_give_the_stiffness_at_any_lame_parameters(cube_model, poisson_ratio):
    shear, volumetric = cube_model.linear_stiffness_parts()
    other = ElasticModel(cube_model.rest_vertices, cube_model.tetrahedra, 5e3, poisson_ratio)
    expected = other.stiffness(kind="linear")
    for part in (shear, volumetric):  # K's pattern: K's values combine entry by entry
        assert np.array_equal(part.indptr, expected.indptr) and np.array_equal(part.indices, expected.indices)
    combined = other.mu * shear.data + other.lam * volumetric.data
    np.testing.assert_allclose(combined, expected.data, rtol=0, atol=1e-12 * np.abs(expected.data).max())


def test_linear_stiffness_is_symmetric_with_rigid_null_space(cube_model):
    stiffness = cube_model.stiffness(kind="linear")
    assert abs(stiffness - stiffness.T).max() == 0.0  # assembled from upper triangles
    scale = abs(stiffness).max()
    rest = cube_model.rest_vertices
    centred = rest - rest.mean(axis=0)
    for axis in np.eye(3):
        translation = np.tile(axis, cube_model.vertex_count)
        rotation = np.cross(axis, centred).reshape(-1)  # infinitesimal rotation about the centre
        assert np.abs(stiffness @ translation).max() < 1e-12 * scale
        assert np.abs(stiffness @ rotation).max() < 1e-12 * scale * np.abs(rotation).max()
    # Exactly 6 zero eigenvalues: the rigid modes and nothing else.
    eigenvalues = np.linalg.eigvalsh(stiffness.toarray())
    assert np.all(np.abs(eigenvalues[:6]) < 1e-10 * eigenvalues[-1])
    assert eigenvalues[6] > 1e-4 * eigenvalues[-1]


# ------------------------------------------------------------------------- corotational


def test_corotational_equals_linear_at_rest(cube_model):
    corotational = cube_model.stiffness(kind="corotational")
    assert relative_difference(corotational, cube_model.stiffness(kind="linear")) < 1e-12
    assert relative_difference(cube_model.stiffness(cube_model.rest_vertices), corotational) == 0.0


def test_corotational_under_rigid_rotation_is_rotated_linear(cube_model):
    rotation = rotation_matrix([1.0, -2.0, 0.5], 2.3)
    state = cube_model.rest_vertices @ rotation.T + np.array([0.3, -1.0, 2.0])
    block_rotation = scipy.sparse.block_diag([rotation] * cube_model.vertex_count, format="csr")
    expected = block_rotation @ cube_model.stiffness(kind="linear") @ block_rotation.T
    assert relative_difference(cube_model.stiffness(state, kind="corotational"), expected) < 1e-9
    # Rigid motion stores no energy and exerts no force.
    assert abs(cube_model.energy(state, "corotational")) < 1e-20
    forces = cube_model.internal_forces(state, "corotational")
    assert np.abs(forces).max() < 1e-9 * YOUNGS_MODULUS * 0.05**2


def test_corotational_stiffness_is_the_sum_of_rotated_rest_element_matrices(cube_model):
    """K(X) = sum_e R_e K0_e R_e^T at a general deformed state, the rotations of independently
    computed deformation gradients and the model's rest element matrices rotated here."""
    rng = np.random.default_rng(4)
    state = cube_model.rest_vertices + 0.004 * rng.standard_normal(cube_model.rest_vertices.shape)
    rotations = polar_rotations(deformation_gradients(cube_model, state))  # (M, 3, 3)
    rest_matrices = cube_model.element_matrices(None, kind="linear")  # (M, 12, 12)
    block_rotations = np.einsum("ab,eij->eaibj", np.eye(4), rotations).reshape(-1, 12, 12)
    rotated = block_rotations @ rest_matrices @ block_rotations.transpose(0, 2, 1)
    expected = cube_model.assemble(rotated)
    assert relative_difference(cube_model.stiffness(state, kind="corotational"), expected) < 1e-12


def test_polar_rotations_match_svd_and_fix_reflections():
    rng = np.random.default_rng(1)
    matrices = np.eye(3) + 0.4 * rng.standard_normal((400, 3, 3))
    matrices[:50, :, 0] *= -1.0  # mostly inverted elements: det < 0
    inverted = np.linalg.det(matrices) < 0
    assert inverted.sum() >= 40
    rotations = polar_rotations(matrices)
    assert np.abs(np.linalg.det(rotations) - 1.0).max() < 1e-12
    assert np.abs(rotations @ rotations.transpose(0, 2, 1) - np.eye(3)).max() < 1e-12
    stretch = rotations.transpose(0, 2, 1) @ matrices  # R^T F must be symmetric
    assert np.abs(stretch - stretch.transpose(0, 2, 1)).max() < 1e-12
    u, _, vt = np.linalg.svd(matrices)
    assert np.abs(rotations[~inverted] - (u @ vt)[~inverted]).max() < 1e-12
    # Inverted: the reflection sits on the smallest singular value, i.e. the smallest stretch.
    eigenvalues = np.linalg.eigvalsh(stretch[inverted])
    singular_values = np.linalg.svd(matrices[inverted], compute_uv=False)
    assert np.abs(eigenvalues[:, 0] + singular_values[:, 2]).max() < 1e-12
    assert np.abs(eigenvalues[:, 1:] - singular_values[:, 1::-1]).max() < 1e-12


def torch_deformation_gradients(rest, tets, positions):
    """Independent torch F_e = Ds Dm^-1 and volumes, float64."""
    rest_t = torch.tensor(rest)
    tets_t = torch.tensor(tets)
    dm = (rest_t[tets_t[:, 1:]] - rest_t[tets_t[:, :1]]).transpose(1, 2)
    ds = (positions[tets_t[:, 1:]] - positions[tets_t[:, :1]]).transpose(1, 2)
    return ds @ torch.linalg.inv(dm), torch.linalg.det(dm).abs() / 6.0


def deformation_gradients(model, state) -> np.ndarray:
    """F_e (M, 3, 3) of the model's elements at `state` (N, 3), by torch_deformation_gradients."""
    deformation, _ = torch_deformation_gradients(model.rest_vertices, model.tetrahedra, torch.tensor(state))
    return deformation.numpy()


def perturbed_state(model, amplitude, seed):
    rng = np.random.default_rng(seed)
    size = np.ptp(model.rest_vertices, axis=0).max()
    return model.rest_vertices + amplitude * size * rng.standard_normal(model.rest_vertices.shape)


def test_corotational_energy_and_forces_match_torch_autograd(cube_model):
    state = perturbed_state(cube_model, 0.05, seed=2)
    mu, lam = cube_model.mu, cube_model.lam

    def corotated_energy(flat):
        deformation, volumes = torch_deformation_gradients(
            cube_model.rest_vertices, cube_model.tetrahedra, flat.reshape(-1, 3)
        )
        u, _, vt = torch.linalg.svd(deformation)
        rotation = u @ vt  # no inverted elements at this perturbation
        trace = torch.einsum("eij,eij->e", rotation, deformation) - 3.0
        density = mu * ((deformation - rotation) ** 2).sum(dim=(1, 2)) + 0.5 * lam * trace**2
        return (volumes * density).sum()

    flat = torch.tensor(state.reshape(-1), requires_grad=True)
    energy = corotated_energy(flat)
    (gradient,) = torch.autograd.grad(energy, flat)
    assert np.all(np.linalg.det(deformation_gradients(cube_model, state)) > 0)
    assert abs(cube_model.energy(state, "corotational") - energy.item()) < 1e-10 * energy.item()
    assert relative_difference(cube_model.internal_forces(state, "corotational"), gradient.numpy()) < 1e-9


# ---------------------------------------------------------------------------- Neo-Hookean


def neo_hookean_torch_energy(model):
    """Stable Neo-Hookean energy (Smith et al. 2018) written independently in torch."""
    mu, lam, alpha = fem.stable_neo_hookean_parameters(model.youngs_modulus, model.poisson_ratio)

    def energy(flat):
        deformation, volumes = torch_deformation_gradients(
            model.rest_vertices, model.tetrahedra, flat.reshape(-1, 3)
        )
        invariant = (deformation**2).sum(dim=(1, 2))
        det = torch.linalg.det(deformation)
        density = (
            0.5 * mu * (invariant - 3.0)
            + 0.5 * lam * (det - alpha) ** 2
            - 0.5 * mu * torch.log(invariant + 1.0)
        )
        rest_density = 0.5 * lam * (1.0 - alpha) ** 2 - 0.5 * mu * np.log(4.0)
        return (volumes * (density - rest_density)).sum()

    return energy


@pytest.fixture(scope="module")
def small_cube_model():
    vertices, tets = structured_cube(2, side=0.05)
    return ElasticModel(vertices, tets, YOUNGS_MODULUS, POISSON_RATIO)


@pytest.mark.parametrize("amplitude", [0.02, 0.15])
def test_neo_hookean_hessian_and_forces_match_torch_autograd(small_cube_model, amplitude):
    model = small_cube_model
    state = perturbed_state(model, amplitude, seed=3)
    energy_fn = neo_hookean_torch_energy(model)
    flat = torch.tensor(state.reshape(-1), requires_grad=True)
    energy = energy_fn(flat)
    (gradient,) = torch.autograd.grad(energy, flat)
    hessian = torch.autograd.functional.hessian(energy_fn, flat.detach()).numpy()
    assert abs(model.energy(state, "neo_hookean") - energy.item()) < 1e-10 * abs(energy.item())
    assert relative_difference(model.internal_forces(state, "neo_hookean"), gradient.numpy()) < 1e-10
    assert relative_difference(model.stiffness(state, kind="neo_hookean"), hessian) < 1e-10


def test_neo_hookean_at_rest_equals_linear_and_is_spd_on_free_dofs(cube_model):
    """With Smith et al.'s Lame re-parametrisation the NH Hessian at F = I is exactly K0."""
    neo_hookean = cube_model.stiffness(kind="neo_hookean")
    assert relative_difference(neo_hookean, cube_model.stiffness(kind="linear")) < 1e-12
    assert abs(cube_model.energy(cube_model.rest_vertices, "neo_hookean")) < 1e-15
    assert np.abs(cube_model.internal_forces(None, "neo_hookean")).max() < 1e-12
    free = free_dofs(cube_model.vertex_count, bottom_vertices(cube_model.rest_vertices))
    report = definiteness(neo_hookean, free)
    assert report.is_spd and not report.is_indefinite
    assert report.method == "dense"


def test_linear_energy_and_forces_are_quadratic_form(cube_model):
    state = perturbed_state(cube_model, 0.03, seed=4)
    displacement = (state - cube_model.rest_vertices).reshape(-1)
    stiffness = cube_model.stiffness(kind="linear")
    forces = stiffness @ displacement
    assert relative_difference(cube_model.internal_forces(state, "linear"), forces) < 1e-12
    energy = cube_model.energy(state, "linear")
    assert abs(energy - 0.5 * displacement @ forces) < 1e-12 * (displacement @ forces)


# ------------------------------------------------------------------------- SPD projection


def test_compressed_sheared_neo_hookean_is_indefinite_and_projection_fixes_it(cube_model):
    state = compressed_sheared_state(cube_model)
    assert np.all(np.linalg.det(deformation_gradients(cube_model, state)) > 0)  # not inverted
    free = free_dofs(cube_model.vertex_count, bottom_vertices(cube_model.rest_vertices))
    raw_stiffness = cube_model.stiffness(state, kind="neo_hookean")
    raw_report = definiteness(raw_stiffness, free)
    assert raw_report.is_indefinite
    assert is_indefinite(raw_stiffness, free)
    assert raw_report.min_eigenvalue < -1e-3 * raw_report.max_abs_eigenvalue

    projected_stiffness = cube_model.stiffness(state, kind="neo_hookean", spd_projection=True)
    dense = projected_stiffness.toarray()
    assert np.abs(dense - dense.T).max() == 0.0
    eigenvalues = np.linalg.eigvalsh(dense)  # all dofs: PSD even with the rigid modes
    assert eigenvalues[0] >= -1e-9 * eigenvalues[-1]
    assert not is_indefinite(projected_stiffness)

    raw = cube_model.element_matrices(state, kind="neo_hookean")
    projected = cube_model.element_matrices(state, kind="neo_hookean", spd_projection=True)
    raw_eigenvalues = np.linalg.eigvalsh(raw)
    scale = np.abs(raw_eigenvalues).max(axis=1)
    # PSD up to the rounding of the 3 exact zero (translation) eigenvalues of every element.
    already_psd = raw_eigenvalues[:, 0] >= -1e-12 * scale
    assert np.all(raw_eigenvalues[~already_psd, 0] < -1e-6 * scale[~already_psd])  # none borderline
    assert already_psd.sum() >= 20 and (~already_psd).sum() >= 20  # both groups are exercised
    assert np.array_equal(projected[already_psd], raw[already_psd])
    # Indefinite elements: brute-force 12x12 clamp (independent of the 9x9 core reduction).
    values, vectors = np.linalg.eigh(raw[~already_psd])
    brute = np.matmul(vectors * np.maximum(values, 0.0)[:, None, :], vectors.transpose(0, 2, 1))
    assert np.all(
        np.abs(projected[~already_psd] - brute).max(axis=(1, 2)) < 1e-10 * scale[~already_psd]
    )
    assert relative_difference(cube_model.assemble(projected), projected_stiffness) == 0.0


@pytest.mark.parametrize("kind", ["linear", "corotational"])
def test_projection_leaves_psd_kinds_unchanged(cube_model, kind):
    state = compressed_sheared_state(cube_model)
    raw = cube_model.stiffness(state, kind=kind)
    assert relative_difference(cube_model.stiffness(state, kind=kind, spd_projection=True), raw) == 0.0
    eigenvalues = np.linalg.eigvalsh(raw.toarray())
    assert eigenvalues[0] >= -1e-9 * eigenvalues[-1]


# --------------------------------------------------------------------------- definiteness


def test_definiteness_iterative_path_matches_dense(cube_model, monkeypatch):
    free = free_dofs(cube_model.vertex_count, bottom_vertices(cube_model.rest_vertices))
    state = compressed_sheared_state(cube_model)
    for stiffness in (cube_model.stiffness(kind="linear"), cube_model.stiffness(state, kind="neo_hookean")):
        dense = definiteness(stiffness, free)
        monkeypatch.setattr(fem, "DENSE_EIGEN_LIMIT", 50)
        iterative = definiteness(stiffness, free)
        monkeypatch.undo()
        assert iterative.method == "inertia" and dense.method == "dense"
        assert abs(iterative.min_eigenvalue - dense.min_eigenvalue) < 1e-8 * dense.max_abs_eigenvalue
        assert abs(iterative.max_abs_eigenvalue - dense.max_abs_eigenvalue) < 1e-8 * dense.max_abs_eigenvalue
        assert iterative.negative_count == dense.negative_count
        assert (iterative.is_spd, iterative.is_indefinite) == (dense.is_spd, dense.is_indefinite)
    assert dense.negative_count > 10  # the Neo-Hookean case has many negative eigenvalues


def test_free_body_linear_stiffness_is_semidefinite_not_spd(cube_model, monkeypatch):
    stiffness = cube_model.stiffness(kind="linear")
    dense = definiteness(stiffness)
    monkeypatch.setattr(fem, "DENSE_EIGEN_LIMIT", 50)
    iterative = definiteness(stiffness)
    for report in (dense, iterative):  # 6 rigid zero modes
        assert not report.is_spd and not report.is_indefinite and report.negative_count == 0
        assert abs(report.min_eigenvalue) < 1e-12 * report.max_abs_eigenvalue


# ------------------------------------------------------------------------------ bad input


def test_degenerate_element_is_named():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], dtype=float)
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4]])  # element 1 is flat (all in z = 0)
    with pytest.raises(DegenerateElementError, match=r"elements \[1\]") as error:
        ElasticModel(vertices, tets, YOUNGS_MODULUS, POISSON_RATIO)
    assert error.value.element_indices.tolist() == [1]
    with pytest.raises(DegenerateElementError, match="repeated"):
        ElasticModel(vertices, np.array([[0, 1, 2, 3], [0, 1, 1, 3]]), YOUNGS_MODULUS, POISSON_RATIO)


@pytest.mark.parametrize("youngs_modulus, poisson_ratio", [(0.0, 0.3), (-1.0, 0.3), (1e3, 0.5), (1e3, -1.0)])
def test_invalid_material_raises(youngs_modulus, poisson_ratio):
    vertices, tets = structured_cube(1)
    with pytest.raises(InvalidMaterialError):
        ElasticModel(vertices, tets, youngs_modulus, poisson_ratio)


def test_bad_state_and_kind_raise(cube_model):
    with pytest.raises(InvalidStateError, match="shape"):
        cube_model.stiffness(np.zeros((3, 3)))
    state = cube_model.rest_vertices.copy()
    state[0, 0] = np.nan
    with pytest.raises(InvalidStateError, match="NaN"):
        cube_model.energy(state, "neo_hookean")
    with pytest.raises(UnknownStiffnessKindError):
        cube_model.stiffness(kind="hyperelastic")
    with pytest.raises(InvalidStateError, match="out of range"):
        ElasticModel(np.eye(4, 3), np.array([[0, 1, 2, 4]]), YOUNGS_MODULUS, POISSON_RATIO)
    flat_state = cube_model.rest_vertices.reshape(-1)
    assert relative_difference(cube_model.stiffness(flat_state), cube_model.stiffness()) == 0.0
