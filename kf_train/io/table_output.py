"""
Where ``kf-train replay`` writes: CSV (built-in or polars), Parquet file or dataset dir.

Every output is written beside its target under a temporary name and moved into place
only when complete (:meth:`Output.commit`); :meth:`Output.abort` removes it, so a
failed replay leaves an existing OUTPUT as it was. '-' writes CSV to standard output.
"""

import os
import queue
import shutil
import sys
import tempfile
import threading
from typing import Callable, Iterable, List, Optional, Sequence

from kf_train.io import columnar, csvio
import numpy as np


def _block_ids(codes: Optional[np.ndarray], names: Sequence[str]):
    """Return (labels, local codes) of a block's ids, or None."""
    if codes is None:
        return None
    present, local = np.unique(codes, return_inverse=True)
    return [names[c] for c in present.tolist()], local.reshape(-1)


class Output:
    """An output file written through a temporary file in the same directory."""

    def __init__(self, path: str, header: List[str], fast: bool):
        """Open the temporary file and write the header (``fast``: with polars)."""
        self.path, self.header, self.fast = path, header, fast
        if path == '-':        # standard output: a temporary file first, copied when done
            handle, self.temporary = tempfile.mkstemp(prefix='kf-train-out-', suffix='.csv')
        else:
            directory = os.path.dirname(os.path.abspath(path))
            handle, self.temporary = tempfile.mkstemp(
                dir=directory, prefix='.' + os.path.basename(path), suffix='.tmp')
        self.stream = os.fdopen(handle, 'wb')
        if fast:
            self.writer = columnar.CsvWriter(self.stream, header)
        else:
            self.stream.write((','.join(header) + '\n').encode('utf-8'))

    def write(self, columns: Sequence[np.ndarray], codes, names: Sequence[str]) -> None:
        """Write a block: its columns and the stream code of every row's id (or None)."""
        ids = _block_ids(codes, names)
        if not self.fast:
            prefix = None if ids is None else (csvio.format_labels(ids[0]), ids[1])
            N = len(columns[0])
            for start in range(0, N, csvio.BLOCK_ROWS):     # small work arrays, in cache
                self.stream.write(csvio.format_rows(
                    columns, start, min(start + csvio.BLOCK_ROWS, N), prefix))
            return
        self.writer.write(columns, None if ids is None else columnar.id_series(*ids))

    def run(self, blocks: Iterable, names: Sequence[str]) -> None:
        """Write every (columns, codes) block (with polars, while the next is computed)."""
        if self.fast:
            in_background(blocks, lambda block: self.write(*block, names))
            return
        for columns, codes in blocks:
            self.write(columns, codes, names)

    def commit(self) -> None:
        """Move the finished file into place (or copy it to standard output)."""
        self.stream.close()
        if self.path != '-':
            _publish(self.temporary, self.path)
            return
        try:
            with open(self.temporary, 'rb') as finished:
                if hasattr(sys.stdout, 'buffer'):
                    sys.stdout.flush()
                    shutil.copyfileobj(finished, sys.stdout.buffer, 1 << 20)
                    sys.stdout.buffer.flush()
                else:
                    for chunk in iter(lambda: finished.read(1 << 20), b''):
                        sys.stdout.write(chunk.decode('utf-8'))
                    sys.stdout.flush()
        finally:
            _remove(self.temporary)

    def abort(self) -> None:
        """Remove the temporary file."""
        self.stream.close()
        _remove(self.temporary)


class ParquetFileOutput(Output):
    """One Parquet file, streamed by polars."""

    def __init__(self, path: str, header: List[str], fast: bool = True):
        """Pick the temporary name (polars creates the file)."""
        self.path, self.header = path, header
        directory = os.path.dirname(os.path.abspath(path))
        handle, self.temporary = tempfile.mkstemp(
            dir=directory, prefix='.' + os.path.basename(path), suffix='.tmp')
        os.close(handle)
        self.stream = True

    def run(self, blocks: Iterable, names: Sequence[str]) -> None:
        """Stream every block into the file."""
        has_id = self.header[0] == 'id'

        def frames():
            for columns, codes in blocks:
                ids = _block_ids(codes, names)
                yield columns, None if ids is None else columnar.id_series(*ids)

        columnar.write_parquet_file(self.temporary, self.header, has_id, frames())

    def commit(self) -> None:
        """Move the finished file into place."""
        _publish(self.temporary, self.path)

    def abort(self) -> None:
        """Remove the temporary file."""
        _remove(self.temporary)


class ParquetDatasetOutput(Output):
    """A directory of Parquet files, one per block (part-00000.parquet, ...)."""

    def __init__(self, path: str, header: List[str], fast: bool = True):
        """Create the temporary directory beside ``path``."""
        self.path, self.header, self.parts = path.rstrip(os.sep), header, 0
        parent = os.path.dirname(os.path.abspath(self.path))
        self.temporary = tempfile.mkdtemp(dir=parent, prefix='.' + os.path.basename(
            self.path), suffix='.tmp')
        self.stream = True

    def run(self, blocks: Iterable, names: Sequence[str]) -> None:
        """Write every block as the next part file."""
        def write(block) -> None:
            columns, codes = block
            if not len(columns[0]):
                return
            ids = _block_ids(codes, names)
            columnar.write_parquet_part(
                os.path.join(self.temporary, f'part-{self.parts:05d}.parquet'), self.header,
                columns, None if ids is None else columnar.id_series(*ids))
            self.parts += 1

        in_background(blocks, write)

    def commit(self) -> None:
        """Replace the target directory (if any) by the finished one."""
        old = None
        if os.path.exists(self.path):
            old = self.temporary + '.old'
            os.rename(self.path, old)
        os.rename(self.temporary, self.path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def abort(self) -> None:
        """Remove the temporary directory."""
        shutil.rmtree(self.temporary, ignore_errors=True)


def in_background(blocks: Iterable, consume: Callable[[tuple], None], depth: int = 2) -> None:
    """
    Consume every block in a second thread while this one produces the next.

    polars writes without holding the GIL, so writing a block overlaps filtering the
    next one; at most ``depth`` finished blocks wait in memory. An exception on either
    side stops both and is raised here.
    """
    pending: 'queue.Queue' = queue.Queue(maxsize=depth)
    failed: List[BaseException] = []
    done = object()

    def writer() -> None:
        while True:
            block = pending.get()
            if block is done:
                return
            if not failed:
                try:
                    consume(block)
                except BaseException as error:     # handed to the producing thread
                    failed.append(error)

    thread = threading.Thread(target=writer, name='kf-train-writer', daemon=True)
    thread.start()
    try:
        for block in blocks:
            if failed:
                break
            pending.put(block)
    finally:
        pending.put(done)
        thread.join()
    if failed:
        raise failed[0]


def _publish(temporary: str, path: str) -> None:
    """Give the finished file ordinary permissions and move it to ``path``."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temporary, 0o666 & ~umask)  # as an ordinary new file, not mkstemp's 0600
    os.replace(temporary, path)


def _remove(path: str) -> None:
    """Remove a file if it is there."""
    try:
        os.unlink(path)
    except OSError:
        pass


def open_output(path: str, header: List[str], fast: bool) -> Output:
    """Return the output for ``path``: Parquet by name (.parquet, a dir), else CSV."""
    if path != '-' and (os.path.isdir(path) or path.endswith(os.sep)):
        return ParquetDatasetOutput(path, header)
    if path.endswith('.parquet'):
        return ParquetFileOutput(path, header)
    return Output(path, header, fast)
