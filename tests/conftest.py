import os
from collections.abc import Iterator

import pytest
import zmq

from facewire.models.mesh import FaceMesh, load_canonical


@pytest.fixture(scope="session")
def mesh() -> FaceMesh:
    """The canonical face mesh (468 vertices)."""
    return load_canonical()


@pytest.fixture
def context() -> Iterator[zmq.Context[zmq.Socket[bytes]]]:
    """A ZeroMQ context of the test's own, ended at its end: every socket must be closed by
    then. One a failed test left open would hold term() for ever, where no timeout can stop
    it (a run in this session hung 20 minutes that way): what is left is closed, and named."""
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    yield ctx
    left = sum(not socket.closed for socket in list(getattr(ctx, "_sockets", ())))
    ctx.destroy(linger=0)
    assert left == 0, f"{left} ZeroMQ socket(s) left open by the test"


@pytest.fixture(autouse=True)
def ordinary_scheduling() -> Iterator[None]:
    """A test that leaves this process real-time fails here, by name: every process the suite
    starts afterwards would inherit it, and a real-time call on two cores can spin for good
    (SVT-AV1 run as root did this; facewire/codecs.py undoes it)."""
    yield
    policy = os.sched_getscheduler(0)
    assert policy == os.SCHED_OTHER, f"the test left the process scheduled as policy {policy}"
