"""kf_train.io.paths: the one output-path check of every command, and what a path names."""

import os

from kf_train.io import check_output_path, is_bag, write_atomic
import pytest


def test_a_file_target_needs_an_existing_writable_directory(tmp_path):
    """A file beside an existing directory passes; a missing directory is named."""
    check_output_path(str(tmp_path / 'out.csv'))
    check_output_path('-')                          # standard output
    with pytest.raises(ValueError, match='does not exist'):
        check_output_path(str(tmp_path / 'missing' / 'out.csv'))


def test_a_directory_is_a_target_only_as_a_dataset(tmp_path):
    """An existing directory is refused as a file and accepted as a Parquet dataset."""
    with pytest.raises(ValueError, match='it is a directory'):
        check_output_path(str(tmp_path))
    check_output_path(str(tmp_path), dataset=True)
    check_output_path(str(tmp_path / 'new') + os.sep, dataset=True)


def test_write_atomic_writes_the_whole_file(tmp_path):
    """The chunks (bytes or text) land in the target, with no temporary file left."""
    target = tmp_path / 'out.txt'
    write_atomic(str(target), [b'a,', 'b\n'])
    assert target.read_text() == 'a,b\n'
    assert os.listdir(tmp_path) == ['out.txt']


def test_is_bag_tells_bags_from_tables(tmp_path):
    """.mcap, .db3 and a directory without Parquet files are bags; a Parquet dataset is not."""
    assert is_bag('run.mcap') and is_bag('run.db3') and not is_bag('run.csv')
    assert is_bag(str(tmp_path))
    (tmp_path / 'part.parquet').write_bytes(b'')
    assert not is_bag(str(tmp_path))
