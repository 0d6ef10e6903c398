"""ANFIS (adaptive-network-based fuzzy inference) in JAX.

* :func:`fit` / :func:`train`: structure by MATLAB-faithful subtractive clustering
  (:func:`subclust`), hybrid learning (least squares + Levenberg-Marquardt or gradient),
  early stopping; returns a :class:`Model`.
* :meth:`Model.predict`: jitted, one sample or a batch.
* :class:`Ensemble`: a weighted average of models (what ``jtraj train`` keeps when it
  tries several clustering radii).
* :meth:`Model.save` / :func:`load`: equinox leaves plus a JSON header (format version
  checked, no retraining).
* :mod:`jtraj.anfis.datasets`: Jang's Mackey-Glass and sinc benchmarks.
"""

from .clustering import Clusters, radius_for_rules, subclust
from .ensemble import Ensemble
from .io import FORMAT_VERSION, load, save
from .model import Model
from .training import History, fit, train

__all__ = ["Clusters", "Ensemble", "FORMAT_VERSION", "History", "Model", "fit", "load", "radius_for_rules", "save",
           "subclust", "train"]
