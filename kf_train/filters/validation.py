"""
Input checks shared by the core: shapes, finiteness and covariance properties.

Every check raises ``ValueError`` naming the offending input, so that a caller can
tell which argument was wrong without reading a traceback.
"""

from typing import Optional

import numpy as np

# Relative tolerance for symmetry and positive semi-definiteness: covariances that
# come out of floating-point arithmetic are only symmetric to rounding.
COVARIANCE_RTOL = 1e-9


def as_finite_array(name: str, value) -> np.ndarray:
    """Return ``value`` as a float64 array, or raise if it is not numeric and finite."""
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f'{name} must be numeric: {error}') from None
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} must be finite, got {array.tolist()}')
    return array


def as_vector(name: str, value, dim: Optional[int] = None) -> np.ndarray:
    """Return a finite 1-D vector; a scalar is accepted as a vector of length 1."""
    array = as_finite_array(name, value)
    if array.ndim == 0:
        array = array.reshape(1)
    if array.ndim == 2 and 1 in array.shape:
        array = array.reshape(-1)
    if array.ndim != 1:
        raise ValueError(f'{name} must be a vector, got shape {array.shape}')
    if dim is not None and array.shape[0] != dim:
        raise ValueError(f'{name} must have length {dim}, got {array.shape[0]}')
    return array


def as_matrix(name: str, value, rows: int, cols: int) -> np.ndarray:
    """Return a finite (rows, cols) matrix; a vector fits a single row or column."""
    array = as_finite_array(name, value)
    if array.ndim == 0 and rows == 1 and cols == 1:
        array = array.reshape(1, 1)
    elif array.ndim == 1 and array.shape[0] == rows * cols and 1 in (rows, cols):
        array = array.reshape(rows, cols)
    if array.shape != (rows, cols):
        raise ValueError(f'{name} must have shape ({rows}, {cols}), got {array.shape}')
    return array


def as_covariance(name: str, value, dim: int) -> np.ndarray:
    """Return a finite, symmetric, positive semi-definite (dim, dim) matrix."""
    matrix = as_matrix(name, value, dim, dim)
    scale = max(1.0, float(np.max(np.abs(matrix))))
    if np.max(np.abs(matrix - matrix.T)) > COVARIANCE_RTOL * scale:
        raise ValueError(f'{name} must be symmetric, got {matrix.tolist()}')
    symmetric = 0.5 * (matrix + matrix.T)
    if float(np.min(np.linalg.eigvalsh(symmetric))) < -COVARIANCE_RTOL * scale:
        raise ValueError(
            f'{name} must be positive semi-definite, got {matrix.tolist()}')
    return symmetric


def as_scalar(name: str, value) -> float:
    """Return ``value`` as a finite float, or raise naming it (not numeric, not a scalar)."""
    array = as_finite_array(name, value)
    if array.ndim != 0:
        raise ValueError(f'{name} must be a scalar, got shape {array.shape}')
    return float(array)


def as_non_negative(name: str, value) -> float:
    """Return ``value`` as a finite float >= 0, or raise naming it."""
    number = as_scalar(name, value)
    if number < 0.0:
        raise ValueError(f'{name} must be >= 0, got {number}')
    return number


def as_positive(name: str, value) -> float:
    """Return ``value`` as a finite float > 0, or raise naming it."""
    number = as_scalar(name, value)
    if number <= 0.0:
        raise ValueError(f'{name} must be > 0, got {number}')
    return number


def as_duration(name: str, value) -> float:
    """Return a finite, non-negative time interval in seconds."""
    return as_non_negative(name, value)
