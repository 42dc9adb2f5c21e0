"""
Paths: what an input path names (:func:`is_bag`), the output-path check, the atomic write.

Every output (a CSV, a params or preset file, a Parquet file or dataset, a bag) is
first written beside its target under a temporary name and moved into place when
complete, so a failure leaves an existing target as it was. :func:`check_output_path`
says before the work, in one line, why a target cannot be written.
"""

import glob
import os
import sys
import tempfile
from typing import Iterable


def is_bag(path: str) -> bool:
    """Return whether ``path`` names a bag (.mcap, .db3, ROS 1 .bag, a directory), not a table."""
    if path.endswith(('.mcap', '.db3', '.bag')):
        return True
    # A directory holding Parquet files is a dataset for the columnar path, not a bag.
    return os.path.isdir(path) and not glob.glob(os.path.join(path, '**', '*.parquet'),
                                                 recursive=True)


def check_output_path(path: str, dataset: bool = False) -> None:
    """
    Raise a one-line ValueError unless ``path`` can be written (``'-'``, standard output, can).

    The target's parent directory must exist and be writable (the temporary file goes
    there), and the target may not be a directory unless ``dataset`` allows one (a
    Parquet dataset: an existing directory or a path ending in a separator).
    """
    if path == '-':
        return
    target = os.path.abspath(path.rstrip(os.sep) or os.sep)
    directory = os.path.dirname(target)
    if not os.path.isdir(directory):
        raise ValueError(f'cannot write {path}: directory {directory} does not exist')
    if not os.access(directory, os.W_OK | os.X_OK):
        raise ValueError(f'cannot write {path}: directory {directory} is not writable')
    is_dataset = dataset and (os.path.isdir(path) or path.endswith(os.sep))
    if os.path.isdir(target) and not is_dataset:
        raise ValueError(f'cannot write {path}: it is a directory')


def write_atomic(path: str, chunks: Iterable) -> None:
    """Write text chunks (bytes or str) to ``path`` via a temporary file; no partial file."""
    if path == '-':
        for chunk in chunks:
            sys.stdout.write(chunk.decode('utf-8') if isinstance(chunk, bytes) else chunk)
        sys.stdout.flush()
        return
    directory = os.path.dirname(os.path.abspath(path))
    handle, temporary = tempfile.mkstemp(dir=directory, prefix='.' + os.path.basename(path),
                                         suffix='.tmp')
    try:
        with os.fdopen(handle, 'wb') as stream:
            for chunk in chunks:
                stream.write(chunk.encode('utf-8') if isinstance(chunk, str) else chunk)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # as an ordinary new file, not mkstemp's 0600
        os.replace(temporary, path)
    except BaseException:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise
