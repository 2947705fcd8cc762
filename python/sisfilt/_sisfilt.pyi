"""Type stubs of the compiled module (python/src/lib.rs)."""

from os import PathLike
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

ArrayLike = npt.ArrayLike
__version__: str

class Model:
    """A chain model, checked as the command line checks a config."""

    @staticmethod
    def from_toml(path: Union[str, PathLike]) -> "Model": ...
    @staticmethod
    def from_toml_str(text: str, name: str = "<string>") -> "Model": ...
    def with_(self, **changes: Any) -> "Model":
        """A changed copy: ``p=0.7``, ``M=[[0.02]]``, ``steps=500``, or a dotted key."""
    def check(self) -> dict: ...
    def to_toml(self) -> str: ...
    @property
    def subsystems(self) -> int: ...
    @property
    def n(self) -> int: ...
    @property
    def q(self) -> int: ...
    @property
    def m(self) -> int: ...
    @property
    def steps(self) -> Optional[int]: ...

class Estimates:
    """The estimates of a run."""

    x: np.ndarray
    P: np.ndarray
    arrival: Optional[np.ndarray]
    nis: np.ndarray
    loglik: Optional[float]
    innovations: dict
    held_out: Optional[dict]
    notes: list
    kind: str
    timings: dict
    def to_pandas(self) -> Any: ...

class Filter:
    """A filter run step by step; equal to ``estimate`` on the same steps."""

    def __init__(
        self,
        model: Model,
        *,
        filter: str = "distributed",
        update: str = "linear",
        dropouts: str = "unknown",
        paper: bool = False,
        solver: Optional[str] = None,
        second_moment: Optional[str] = None,
        interconnect_from: Optional[str] = None,
        band: Optional[int] = None,
        band_tol: Optional[float] = None,
        loading: Optional[float] = None,
        max_lifted: int = ...,
        max_memory: Optional[int] = None,
    ) -> None: ...
    def step(self, y_t: ArrayLike, u_t: Optional[ArrayLike] = None) -> Tuple[np.ndarray, np.ndarray]: ...
    def predicted(self) -> Tuple[np.ndarray, np.ndarray]: ...
    @property
    def arrival(self) -> Optional[np.ndarray]: ...
    @property
    def loglik(self) -> Optional[float]: ...
    @property
    def t(self) -> int: ...

def simulate(
    model: Model, seed: Optional[int] = None, steps: Optional[int] = None, *, max_memory: int = ...
) -> dict: ...
def estimate(
    model: Model,
    y: ArrayLike,
    u: Optional[ArrayLike] = None,
    *,
    filter: str = "distributed",
    update: str = "linear",
    dropouts: str = "unknown",
    smooth: bool = False,
    predicted: bool = False,
    paper: bool = False,
    solver: Optional[str] = None,
    second_moment: Optional[str] = None,
    interconnect_from: Optional[str] = None,
    band: Optional[int] = None,
    band_tol: Optional[float] = None,
    loading: Optional[float] = None,
    max_lifted: int = ...,
    max_memory: Optional[int] = None,
    hold_out: Optional[float] = None,
    seed: int = 1,
) -> Estimates: ...
def fit(
    model: Model,
    y: ArrayLike,
    u: Optional[ArrayLike] = None,
    *,
    params: Optional[Sequence[str]] = None,
    filter: str = "joint",
    band: Optional[int] = None,
    dropouts: str = "unknown",
    max_iter: int = 200,
    max_memory: Optional[int] = None,
) -> Tuple[dict, Model]: ...
def evaluate(
    model: Model,
    runs: int,
    *,
    seed: Optional[int] = None,
    burn_in: int = 0,
    max_lifted: int = ...,
    band: int = 2,
    loading: Optional[float] = None,
    filters: Optional[Sequence[str]] = None,
    smooth: bool = False,
    sweep_p: Optional[Sequence[float]] = None,
    true_p: Optional[float] = None,
    shard: Optional[Tuple[int, int]] = None,
    max_memory: int = ...,
) -> dict: ...
def evaluate_merge(parts: Sequence[dict]) -> dict: ...
