"""
A recorded calculation: the structure-of-arrays steps traced once, replayed many times.

The bank's lock-step runs one Kalman step (written with :mod:`~kf_train.batch.soa`) per
row of every object. :func:`trace` runs such a step once on symbols instead of arrays
and records each arithmetic operation it performs (the same operations on the same
operands, constants folded and zeros and ones skipped exactly as the arrays would
have them), and :class:`Tape` replays the record with numpy ufuncs writing into
reused buffers (``out=``): no allocation and no Python dispatch per entry, and only a
few buffers live at once, so a block of columns stays in the CPU's cache. Every
element gets the very operations, in the very order, of the untraced step, so the
results are bit for bit the same (test_bank_golden).
"""

from typing import Callable, List, Sequence

import numpy as np

_ADD, _SUB, _MUL, _DIV, _NEG = np.add, np.subtract, np.multiply, np.divide, np.negative


class Symbol:
    """A value of the traced step: an input (an array) or the result of one operation."""

    __slots__ = ('tape', 'index')
    __array_ufunc__ = None          # numpy scalars defer to the reflected operators below

    def __init__(self, tape: 'Tape', index: int):
        """Name the value ``index`` of ``tape``."""
        self.tape, self.index = tape, index

    def __add__(self, other):
        """Record self + other."""
        return self.tape.record(_ADD, self, other)

    def __radd__(self, other):
        """Record other + self."""
        return self.tape.record(_ADD, other, self)

    def __sub__(self, other):
        """Record self − other."""
        return self.tape.record(_SUB, self, other)

    def __rsub__(self, other):
        """Record other − self."""
        return self.tape.record(_SUB, other, self)

    def __mul__(self, other):
        """Record self · other."""
        return self.tape.record(_MUL, self, other)

    def __rmul__(self, other):
        """Record other · self."""
        return self.tape.record(_MUL, other, self)

    def __truediv__(self, other):
        """Record self / other."""
        return self.tape.record(_DIV, self, other)

    def __rtruediv__(self, other):
        """Record other / self."""
        return self.tape.record(_DIV, other, self)

    def __neg__(self):
        """Record −self."""
        return self.tape.record(_NEG, self, None)


class Tape:
    """The operations of one traced step, and the buffers that replay them."""

    def __init__(self):
        """Start an empty record."""
        self.count = 0
        self.inputs: List[int] = []
        self.ops: list = []
        self.outputs: list = []
        self.slots: List[int] = []
        self.slot_count = 0

    def new_input(self) -> Symbol:
        """Return a new input symbol (its array is given at each replay)."""
        symbol = Symbol(self, self.count)
        self.count += 1
        self.inputs.append(symbol.index)
        return symbol

    def record(self, ufunc, a, b) -> Symbol:
        """Record ufunc(a, b) (b None: unary) and return its result's symbol."""
        for operand in (a, b):
            if not (operand is None or isinstance(operand, (Symbol, float))):
                raise TypeError(f'cannot trace an operand of type {type(operand).__name__}')
        symbol = Symbol(self, self.count)
        self.count += 1
        self.ops.append((ufunc, a, b, symbol.index))
        return symbol

    def finish(self, outputs: Sequence) -> None:
        """Fix the outputs (symbols or constants) and give every result a buffer slot."""
        self.outputs = list(outputs)
        kept = {o.index for o in self.outputs if isinstance(o, Symbol)}
        last = {}
        for position, (_, a, b, _) in enumerate(self.ops):
            for operand in (a, b):
                if isinstance(operand, Symbol):
                    last[operand.index] = position
        slot_of, free, slots = {}, [], []
        for position, (_, a, b, result) in enumerate(self.ops):
            # Operands read for the last time give their buffer back first: an
            # elementwise ufunc may write its result over its own operand.
            for operand in (a, b):
                if (isinstance(operand, Symbol) and operand.index in slot_of
                        and operand.index not in kept and last[operand.index] == position
                        and slot_of[operand.index] not in free):
                    free.append(slot_of[operand.index])
            slot = free.pop() if free else len(slots)
            if slot == len(slots):
                slots.append(slot)
            slot_of[result] = slot
        self.slots = [slot_of[op[3]] for op in self.ops]
        self.slot_count = len(slots)

    def buffers(self, size: int) -> List[np.ndarray]:
        """Return the replay's buffers for up to ``size`` columns."""
        return [np.empty(size) for _ in range(self.slot_count)]

    def replay(self, inputs: Sequence, buffers: List[np.ndarray], a: int) -> list:
        """Return the outputs for ``inputs`` (arrays of ``a`` columns, in input order)."""
        values = [None] * self.count
        for index, value in zip(self.inputs, inputs):
            values[index] = value
        views = [buffer[:a] for buffer in buffers]
        for (ufunc, x, y, result), slot in zip(self.ops, self.slots):
            x = values[x.index] if isinstance(x, Symbol) else x
            if y is None:
                values[result] = ufunc(x, out=views[slot])
            else:
                y = values[y.index] if isinstance(y, Symbol) else y
                values[result] = ufunc(x, y, out=views[slot])
        return [values[o.index] if isinstance(o, Symbol) else o for o in self.outputs]


def trace(step: Callable, shape: Sequence) -> Tape:
    """
    Return the tape of ``step`` called on input symbols.

    ``shape`` gives ``step``'s arguments: each a nested list whose leaves are True (an
    array input: a new symbol) or a float (a constant, kept), and ``step`` returns a
    flat list of outputs.
    """
    tape = Tape()

    def symbols(leaf: object) -> object:
        if isinstance(leaf, list):
            return [symbols(e) for e in leaf]
        return tape.new_input() if leaf is True else leaf

    tape.finish(step(*[symbols(argument) for argument in shape]))
    return tape
