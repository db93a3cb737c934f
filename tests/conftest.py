import pytest

from models.mesh import FaceMesh, load_canonical


@pytest.fixture(scope="session")
def mesh() -> FaceMesh:
    """The canonical face mesh (468 vertices)."""
    return load_canonical()
