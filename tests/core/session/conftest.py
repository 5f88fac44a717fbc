"""A session on the small simulated data set, fresh for each test."""

import pytest

from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.store import SessionDB, open_session


@pytest.fixture
def dataset(small_dataset_dir):
    return open_dataset(small_dataset_dir)


@pytest.fixture
def db(tmp_path, dataset):
    return SessionDB(open_session("s", tmp_path), dataset)
