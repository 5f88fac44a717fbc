import pytest

from factorydet_core.io.atomic import atomic_path, write_text_atomic


def test_a_file_is_replaced_whole_or_left_as_it_was(tmp_path):
    path = tmp_path / "result.json"
    write_text_atomic(path, "first")
    assert path.read_text() == "first"
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half of the sec")
        raise RuntimeError("stopped while writing")
    assert path.read_text() == "first" and sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]
    write_text_atomic(path, "second")
    assert path.read_text() == "second" and len(list(tmp_path.iterdir())) == 1
