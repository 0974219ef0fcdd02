"""A CPU-only check that a code path keeps its tensors on its inputs' device (docs/development.md, "Devices").

On a GPU every tensor a function makes without ``device=`` (``torch.eye(3)``, ``torch.zeros(n)``,
``torch.tensor([...])``, ``torch.from_numpy(a)``) lives on the CPU, and the first operation that mixes it with
an input on the GPU raises. On a CPU-only machine the two are the same device and the bug stays hidden.
:class:`DeviceCheck` makes it visible there: it simulates a second device on the CPU.

How it works. The check is a :class:`torch.overrides.TorchFunctionMode`, so it sees every top-level torch call
(functions, tensor methods and operators, property reads such as ``x.device``) of the code run inside it,
while the values stay real CPU tensors: results are computed as usual and tests keep checking them. Each
storage gets one of two labels, in a weak table keyed by its ``UntypedStorage`` (so views, ``.detach()``,
``nn.Parameter`` wrappers and ``param.data = ...`` swaps share their storage's label):

- *accelerator*: made with ``device=DeviceCheck.device`` (``torch.device("cpu", 0)``, the stand-in for
  ``cuda``: pass it as the code's ``device`` / ``--device cpu:0``), moved there (``.to(device)``,
  ``nn.Module.to``), made "like" such a tensor (``zeros_like``, ``x.new_zeros``, ``device=x.device``), or
  computed from one;
- *host*: every tensor that existed when the check started (except those an earlier check labelled accelerator
  and that still live, in caches for instance), and every tensor made without ``device=`` or with
  a CPU device (factories, ``torch.from_numpy``, ``torch.tensor`` of Python data), moved to the CPU
  (``.cpu()``, ``.to("cpu")``) or computed from host tensors only.

Reading ``.device`` of an accelerator tensor returns the stand-in device, so ``device=x.device`` follows it
the way it follows ``cuda`` on a GPU. ``torch.from_numpy`` and ``torch.frombuffer``, which no
mode sees, are replaced by labelling wrappers while the check runs (calls through the ``torch`` module; a name
imported from it before is not). A tensor that no intercepted call made (``torch.load`` results, tensors made by
compiled extensions or on other threads) stays unlabelled and never causes a finding.

What it flags, each a call that raises on a CUDA device (a :class:`Finding` with the call site and, for a host
tensor, where it was made):

- an operation that mixes an accelerator tensor with a host tensor: any two tensor arguments, in lists too
  (``torch.cat``), an ``out=`` buffer included;
- ``.numpy()`` / ``np.asarray`` of an accelerator tensor;
- a host gradient assigned to an accelerator tensor's ``.grad``;
- a random operation on the accelerator given a ``generator=`` (generators are CPU generators unless made with
  ``torch.Generator(device=...)``, which this check cannot tell apart: none is made so today).

What it lets through, as CUDA does: a host tensor of zero dimensions beside accelerator tensors (CUDA kernels
take CPU scalars), except in the concatenations (``cat``, ``stack``, ...), which do not; host index tensors
in ``x[index]`` and ``x[index] = v`` (CUDA moves them), and host values in basic-index assignment
(``x[1:3] = v`` is a copy); copies and moves (``copy_``, ``.to``, ``*_like(device=...)``); the ``_foreach_``
operations compare their lists position by position; ``torch.autograd.grad`` and ``backward`` (a CPU scalar
parameter of a CUDA loss gets a CPU gradient).

Limits: it sees the Python-level calls of the thread that entered it, not the operations inside a torch
function (``F.grid_sample``'s internals run as one call), other threads or worker processes. It does not run
the CUDA-only branches (``if device.type == "cuda"``: gsplat, CUDA synchronisation), since the stand-in device
is a CPU one.
"""

from __future__ import annotations

import gc
import os
import sys
import weakref
from dataclasses import dataclass
from typing import Any, Callable, Iterator

import torch
from torch.overrides import TorchFunctionMode

#: the stand-in accelerator: a CPU device that compares unequal to ``torch.device("cpu")``
ACCELERATOR = torch.device("cpu", 0)

_ACC, _HOST = "accelerator", "host"
_TORCH_DIR = os.path.dirname(torch.__file__)
_THIS_FILE = os.path.abspath(__file__)

#: concatenations: no zero-dimensional CPU tensor beside CUDA ones
_CONCATS = frozenset({"cat", "concat", "concatenate", "stack", "hstack", "vstack", "dstack", "column_stack",
                      "row_stack", "block_diag", "cartesian_prod"})
#: factories that no TorchFunctionMode sees (replaced by labelling wrappers while a check runs)
_BYPASSING = ("from_numpy", "frombuffer")
#: calls that make a tensor on a device of their own: (the device given, else the source's)
_LIKE = frozenset({"zeros_like", "ones_like", "empty_like", "full_like", "rand_like", "randn_like", "randint_like",
                   "new_zeros", "new_ones", "new_empty", "new_full", "new_tensor", "new_empty_strided", "clone",
                   "detach", "contiguous", "type", "double", "float", "half", "bfloat16", "long", "int", "bool"})
#: calls that run on tensors of several devices by design
_NO_CHECK = frozenset({"copy_", "backward", "set_", "__repr__", "__format__", "__str__", "__deepcopy__",
                       "__reduce_ex__", "__setstate__", "_has_compatible_shallow_copy_type", "is_set_to",
                       "data_ptr", "untyped_storage", "storage"})
#: random operations that take a ``generator=``
_RANDOM = frozenset({"rand", "randn", "randint", "randperm", "rand_like", "randn_like", "randint_like", "normal",
                     "bernoulli", "multinomial", "poisson", "uniform_", "normal_", "random_", "exponential_",
                     "geometric_", "cauchy_", "log_normal_", "bernoulli_"})


class DeviceMixError(RuntimeError):
    """An operation mixed an accelerator tensor with a host one (raised by a :class:`DeviceCheck` made with
    ``raise_on_finding=True``)."""


@dataclass(frozen=True)
class Finding:
    """One call that would raise on a CUDA device.

    Attributes:
        op: the torch call (e.g. ``allclose``, ``Tensor.__getitem__``).
        message: what was mixed (shapes and labels of the operands).
        where: ``file:line`` of the call, the innermost frame outside torch.
        made_at: ``file:line`` where the offending host tensor was made, when known.
    """

    op: str
    message: str
    where: str
    made_at: str | None = None

    def __str__(self) -> str:
        made = f" (the host tensor was made at {self.made_at})" if self.made_at else ""
        return f"{self.where}: {self.op}: {self.message}{made}"


def _caller() -> str:
    """``file:line`` of the innermost frame outside torch and this module (paths relative to the working
    directory when below it)."""
    frame = sys._getframe(1)
    while frame is not None:
        name = frame.f_code.co_filename
        if not name.startswith(_TORCH_DIR) and os.path.abspath(name) != _THIS_FILE:
            try:
                name = os.path.relpath(name)
            except ValueError:
                pass
            return f"{name}:{frame.f_lineno}"
        frame = frame.f_back
    return "?"


def _tensors(values: Any) -> Iterator[torch.Tensor]:
    """The tensors among ``values`` and one level of lists and tuples inside them."""
    for v in values:
        if isinstance(v, torch.Tensor):
            yield v
        elif isinstance(v, (list, tuple)):
            for w in v:
                if isinstance(w, torch.Tensor):
                    yield w


def _name(func: Callable) -> str:
    owner = getattr(func, "__self__", None)
    if type(owner).__name__ == "getset_descriptor":  # a property read or written: Tensor.device.__get__
        return f"{owner.__name__}.{func.__name__}"
    return getattr(func, "__name__", repr(func))


#: id(UntypedStorage) → a weak reference to it, of every storage that a check labelled accelerator and that is
#: still alive: a later check starts with them on the accelerator (the entry dropped when the storage dies)
_ON_ACCELERATOR: dict[int, weakref.ref] = {}


def _was_on_accelerator(tensor: torch.Tensor) -> bool:
    try:
        storage = tensor.untyped_storage()
    except (RuntimeError, NotImplementedError, TypeError):
        return False
    ref = _ON_ACCELERATOR.get(id(storage))
    return ref is not None and ref() is storage


class DeviceCheck(TorchFunctionMode):
    """Run code with a simulated accelerator and find the calls that would mix devices on a GPU.

    Use it as a context manager and give the code :attr:`device` as its device::

        with DeviceCheck() as check:
            run_something(device=check.device)
        check.assert_clean()

    Args:
        raise_on_finding: raise :class:`DeviceMixError` at the first finding (as CUDA would) instead of
            collecting them in :attr:`findings`.

    Attributes:
        device: the stand-in accelerator (``torch.device("cpu", 0)``; ``"cpu:0"`` on a command line).
        findings: the distinct findings, in the order met.
        accelerator_calls: how many calls had an accelerator tensor among their arguments (a run that reaches
            none checked nothing).
    """

    device = ACCELERATOR

    def __init__(self, raise_on_finding: bool = False) -> None:
        super().__init__()
        self.raise_on_finding = raise_on_finding
        self.findings: list[Finding] = []
        self.accelerator_calls = 0
        # id(UntypedStorage) → (label, made_at), the entry dropped when the storage dies (a weak reference's
        # callback), so that an id reused by a later storage finds no stale label
        self._labels: dict[int, tuple[str, str | None]] = {}
        self._refs: dict[int, weakref.ref] = {}
        self._names: dict[Any, str] = {}
        self._seen: set[tuple[str, str]] = set()
        self._unwrapped: dict[str, Callable] = {}

    # ---- labels -------------------------------------------------------------------------------------------

    def __enter__(self) -> "DeviceCheck":
        for obj in gc.get_objects():  # what exists already was made on the host, or on the accelerator of an
            if issubclass(type(obj), torch.Tensor):  # earlier check (a cache such as fused._index keeps it)
                self._set(obj, _ACC if _was_on_accelerator(obj) else _HOST, None, overwrite=False)
        # torch.from_numpy and torch.frombuffer bypass the modes: wrapped while the check runs, so that their
        # results are host tensors (as on a GPU machine) rather than unlabelled
        self._unwrapped = {name: getattr(torch, name) for name in _BYPASSING}
        for name, original in self._unwrapped.items():
            setattr(torch, name, self._host_factory(original))
        try:
            return super().__enter__()
        except BaseException:
            self._unwrap()
            raise

    def __exit__(self, *exc: Any) -> Any:
        try:
            return super().__exit__(*exc)
        finally:
            self._unwrap()

    def _unwrap(self) -> None:
        for name, original in self._unwrapped.items():
            setattr(torch, name, original)
        self._unwrapped = {}

    def _host_factory(self, original: Callable) -> Callable:
        def factory(*args: Any, **kwargs: Any) -> torch.Tensor:
            out = original(*args, **kwargs)
            self._set(out, _HOST, _caller(), overwrite=False)
            return out

        factory.__name__ = original.__name__
        factory.__doc__ = original.__doc__
        return factory

    def label(self, tensor: torch.Tensor) -> str | None:
        """``"accelerator"``, ``"host"`` or ``None`` (never seen) for ``tensor``'s storage."""
        entry = self._entry(tensor)
        return entry[0] if entry else None

    def _entry(self, tensor: torch.Tensor) -> tuple[str, str | None] | None:
        try:
            return self._labels.get(id(tensor.untyped_storage()))
        except (RuntimeError, NotImplementedError, TypeError):  # sparse, functorch wrappers: no storage
            return None

    def _set(self, tensor: torch.Tensor, label: str, made_at: str | None, overwrite: bool) -> None:
        try:
            storage = tensor.untyped_storage()
        except (RuntimeError, NotImplementedError, TypeError):
            return
        key = id(storage)
        if key not in self._labels:
            labels, refs = self._labels, self._refs

            def forget(_: weakref.ref, key: int = key) -> None:
                labels.pop(key, None)
                refs.pop(key, None)

            refs[key] = weakref.ref(storage, forget)
        elif not overwrite:
            return
        self._labels[key] = (label, made_at)
        if label == _ACC and key not in _ON_ACCELERATOR:
            _ON_ACCELERATOR[key] = weakref.ref(storage, lambda _, key=key: _ON_ACCELERATOR.pop(key, None))

    def _target(self, device: Any) -> str:
        return _ACC if torch.device(device) == ACCELERATOR else _HOST

    # ---- findings -----------------------------------------------------------------------------------------

    def _find(self, op: str, message: str, made_at: str | None = None) -> None:
        finding = Finding(op, message, _caller(), made_at)
        if self.raise_on_finding:
            raise DeviceMixError(str(finding))
        key = (finding.where, op)
        if key not in self._seen:
            self._seen.add(key)
            self.findings.append(finding)

    def report(self) -> str:
        """The findings, one per line (empty when there are none)."""
        return "\n".join(str(f) for f in self.findings)

    def assert_clean(self, min_accelerator_calls: int = 1) -> None:
        """Raise :class:`DeviceMixError` listing the findings, or when fewer than ``min_accelerator_calls``
        calls reached an accelerator tensor (the device was not passed on: nothing was checked)."""
        if self.findings:
            raise DeviceMixError(f"{len(self.findings)} device mix(es):\n{self.report()}")
        if self.accelerator_calls < min_accelerator_calls:
            raise DeviceMixError(f"only {self.accelerator_calls} calls reached an accelerator tensor: was "
                                 f"DeviceCheck.device ({ACCELERATOR}) passed as the device?")

    def _mix(self, op: str, tensors: list[torch.Tensor], scalars_allowed: bool) -> str | None:
        """A finding if ``tensors`` hold an accelerator tensor and a host one (host zero-dimensional ones
        allowed when ``scalars_allowed``). Returns the label of a result computed from them: accelerator if one
        of them is, else host if one of them is, else ``None``."""
        acc, host, any_host = None, None, False
        for t in tensors:
            entry = self._entry(t)
            if entry is None:
                continue
            if entry[0] == _ACC:
                acc = t if acc is None else acc
            else:
                any_host = True
                if host is None and not (scalars_allowed and t.dim() == 0):
                    host = (t, entry[1])
        if acc is None:
            return _HOST if any_host else None
        self.accelerator_calls += 1
        if host is not None:
            t, made_at = host
            self._find(op, f"an accelerator tensor {tuple(acc.shape)} {acc.dtype} meets a host tensor "
                       f"{tuple(t.shape)} {t.dtype}", made_at)
        return _ACC

    # ---- the mode -----------------------------------------------------------------------------------------

    def __torch_function__(self, func: Callable, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        try:
            name = self._names[func]
        except KeyError:
            name = self._names[func] = _name(func)
        except TypeError:  # unhashable
            name = _name(func)
        if name.endswith(".__get__"):
            return self._get(name[:-8], func, args)
        if name.endswith(".__set__"):
            if name == "grad.__set__" and isinstance(args[1], torch.Tensor):
                self._mix("Tensor.grad = ...", [args[0], args[1]], scalars_allowed=False)
            return func(*args, **kwargs)
        if name in _NO_CHECK:
            return func(*args, **kwargs)
        if name in ("numpy", "__array__"):
            if self.label(args[0]) == _ACC:
                self._find(f"Tensor.{name}", f"an accelerator tensor {tuple(args[0].shape)} converted to NumPy "
                           "(call .cpu() first)")
            return func(*args, **kwargs)
        if func is torch.autograd.grad:
            return self._grad(func, args, kwargs)
        if name == "_parse_to":  # nn.Module.to(tensor): the tensor's device
            out = func(*args, **kwargs)
            if args and isinstance(args[0], torch.Tensor) and self.label(args[0]) == _ACC:
                out = (ACCELERATOR, *out[1:])
            return out
        if name in ("to", "cpu", "cuda", "as_tensor", "tensor", "asarray", "type_as") or name in _LIKE \
                or kwargs.get("device") is not None:
            return self._move(name, func, args, kwargs)
        if name in ("__getitem__", "__setitem__", "index_put", "index_put_"):
            self._index(name, args)
            out = func(*args, **kwargs)
            self._label_outputs(out, self._propagated(args[:1]), None)
            return out
        if name.startswith("_foreach_"):
            self._foreach(name, args, kwargs)
            out = func(*args, **kwargs)
            return out
        tensors = list(_tensors(args)) + list(_tensors(kwargs.values()))
        if not tensors:  # a factory without device=: the host, as on a GPU machine
            out = func(*args, **kwargs)
            if isinstance(out, torch.Tensor) or (isinstance(out, (list, tuple)) and any(_tensors(out))):
                self._label_outputs(out, _HOST, _caller())
            return out
        label = self._mix(name, tensors, scalars_allowed=name not in _CONCATS)
        if name in _RANDOM and kwargs.get("generator") is not None and label == _ACC:
            self._find(name, "a CPU generator drives a random operation on the accelerator")
        out = func(*args, **kwargs)
        self._label_outputs(out, label, None)
        return out

    def _propagated(self, tensors: Any) -> str | None:
        """The label of a result computed from ``tensors``: accelerator if one of them is, else host if one
        of them is, else unknown."""
        labels = {self.label(t) for t in _tensors(tensors)}
        return _ACC if _ACC in labels else _HOST if _HOST in labels else None

    def _label_outputs(self, out: Any, label: str | None, made_at: str | None) -> None:
        if label is None:
            return
        for t in _tensors(out if isinstance(out, (list, tuple)) else (out,)):
            self._set(t, label, made_at, overwrite=False)

    def _get(self, prop: str, func: Callable, args: tuple) -> Any:
        out = func(*args)
        if prop == "device":
            return ACCELERATOR if self.label(args[0]) == _ACC else out
        if isinstance(out, torch.Tensor):  # .data, .grad, .T, ...: the owner's device
            self._label_outputs(out, self.label(args[0]), None)
        return out

    def _grad(self, func: Callable, args: tuple, kwargs: dict) -> Any:
        out = func(*args, **kwargs)
        inputs = kwargs.get("inputs", args[1] if len(args) > 1 else ())
        inputs = (inputs,) if isinstance(inputs, torch.Tensor) else tuple(inputs)
        for g, x in zip(out, inputs):
            if isinstance(g, torch.Tensor):
                self._label_outputs(g, self.label(x), None)
        return out

    def _move(self, name: str, func: Callable, args: tuple, kwargs: dict) -> Any:
        """A call that makes a tensor on a device of its own choosing: the device given, else its source's."""
        source = args[0] if args and isinstance(args[0], torch.Tensor) else None
        device = kwargs.get("device")
        if name == "to":
            if len(args) > 1 and isinstance(args[1], torch.Tensor):
                target = self.label(args[1])
            else:
                parsed = torch._C._nn._parse_to(*args[1:], **{k: v for k, v in kwargs.items() if k != "copy"})[0]
                target = self._target(parsed) if parsed is not None else self.label(source)
        elif name == "type_as":
            target = self.label(args[1])
        elif name == "cpu":
            target = _HOST
        elif device is not None:
            target = self._target(device)
        elif name in ("tensor", "as_tensor", "asarray"):
            target = self.label(source) if source is not None else _HOST
        else:
            target = self.label(source) if source is not None else _HOST
        if source is not None and name not in ("to", "cpu", "cuda", "tensor", "as_tensor", "asarray") \
                and device is None:
            self._mix(name, list(_tensors(args)) + list(_tensors(kwargs.values())), scalars_allowed=True)
        out = func(*args, **kwargs)
        if target is None:
            return out
        made_at = _caller() if target == _HOST and source is None else None
        if isinstance(out, torch.Tensor):
            entry = self._entry(out)
            if entry is not None and entry[0] != target:  # .to() returned its source: a copy, as on a GPU
                out = out.clone()
            self._set(out, target, made_at, overwrite=False)
        return out

    def _index(self, name: str, args: tuple) -> None:
        """``x[index]``, ``x[index] = value``, ``index_put``: host indices are allowed on an accelerator
        ``x``; the value must be on ``x``'s device unless it is zero-dimensional or the index is basic."""
        self_, index = args[0], args[1] if len(args) > 1 else ()
        indices = list(_tensors(index if isinstance(index, (list, tuple)) else (index,)))
        mine = self.label(self_)
        if mine is None:
            return
        if mine == _ACC:
            self.accelerator_calls += 1
        if mine == _HOST:  # CUDA indices into a CPU tensor
            self._mix(f"Tensor.{name}", [self_] + [i for i in indices if i.dim() > 0], scalars_allowed=False)
        if name in ("__setitem__", "index_put", "index_put_") and len(args) > 2 and isinstance(args[2], torch.Tensor):
            advanced = any(i.dim() > 0 for i in indices) or (
                isinstance(index, (list, tuple)) and any(isinstance(i, (list, tuple)) for i in index)) \
                or isinstance(index, list) or name != "__setitem__"
            if advanced:
                self._mix(f"Tensor.{name}", [self_, args[2]], scalars_allowed=True)

    def _foreach(self, name: str, args: tuple, kwargs: dict) -> None:
        """``torch._foreach_*``: the tensors at each position of the lists must share a device."""
        lists = [v for v in list(args) + list(kwargs.values()) if isinstance(v, (list, tuple))]
        for row in zip(*lists):
            self._mix(name, [t for t in row if isinstance(t, torch.Tensor)], scalars_allowed=True)
