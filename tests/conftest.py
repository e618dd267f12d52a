import os

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("OMP_NUM_THREADS", "2")

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def small_case():
    """A small simulated case (seed 3, 4 frames, small CT) with its ground truth."""
    from guidewire3d.phantom import PhantomOptions, simulate

    return simulate(PhantomOptions(seed=3, n_frames=4))


@pytest.fixture(scope="session")
def small_case_dir(small_case, tmp_path_factory):
    """``small_case`` written with ``write_case`` (ct/, roadmap.dcm, frames.dcm, heldout.dcm, truth)."""
    from guidewire3d.phantom import write_case

    return write_case(small_case, tmp_path_factory.mktemp("phantom") / "case")


@pytest.fixture(scope="session")
def distractor_case():
    """A simulated case with bone and blob distractors in the CT (seed 5, 2 frames)."""
    from guidewire3d.phantom import PhantomOptions, simulate

    return simulate(PhantomOptions(seed=5, n_frames=2, distractors=True))


# seeds of the tiny studies of tests/test_batch.py and tests/test_listen.py (registration ok on each)
TINY_SEEDS = (11, 12, 13, 14)


@pytest.fixture(scope="session")
def tiny_studies(tmp_path_factory):
    """Four tiny simulated studies (2 live frames each), written with ``write_case``: {name: case folder}."""
    from guidewire3d.phantom import PhantomOptions, simulate, write_case

    root = tmp_path_factory.mktemp("tiny_studies")
    return {f"s{seed}": write_case(simulate(PhantomOptions(seed=seed, n_frames=2)), root / f"s{seed}")
            for seed in TINY_SEEDS}
