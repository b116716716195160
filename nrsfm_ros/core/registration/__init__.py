"""Point set registration by method name: ICP (point-to-point, point-to-plane), Coherent Point
Drift (rigid, affine, non-rigid), ECPD (CPD with prior correspondences), the rigid
gravitational approach (GA), its Barnes-Hut energy-minimising form (BH-RGA) and the non-rigid
gravitational approach (NRGA).  One result type, ``RegistrationResult``, and one meaning of
``fitness`` / ``inlier_rmse`` for every method (``base``: the ``inlier_threshold`` parameter).
ICP's ``init='global'`` starts it from a search over all rotations (``global_pose``).

Modules: ``base`` (result, checks, Kabsch, normalisation, fitness), ``refine`` (trimmed ICP
iterations) and ``kernels`` (Nystrom features) are building blocks; each method module (icp,
cpd, gravitational, bhrga, nrga) and the global start (globalsearch) imports only those, never
another method (icp imports the global start for ``init='global'``). ``rays`` poses a
camera-frame cloud from matched points (the registrar's ``match: track_id``), trusting its viewing
rays over its depth; it imports only ``base``."""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import PARAM_RULES, RegistrationResult, check_param, robust_residual
from .bhrga import bhrga
from .cpd import cpd
from .globalsearch import GlobalPose, global_pose
from .gravitational import ga
from .icp import ICP_METHODS, icp
from .nrga import nrga

CPD_METHODS = {'cpd-rigid': 'rigid', 'cpd-affine': 'affine', 'cpd-nonrigid': 'nonrigid',
               'ecpd-rigid': 'rigid', 'ecpd-nonrigid': 'nonrigid'}
METHODS = sorted([*ICP_METHODS, *CPD_METHODS, 'ga', 'bhrga', 'nrga'])
# the parameters each family understands (the registrar node passes its own set)
ICP_PARAMS = {'max_iterations', 'tolerance', 'max_correspondence_distance', 'init', 'trim',
              'max_points', 'target_tree', 'voxel', 'inlier_threshold'}
CPD_PARAMS = {'w', 'max_iterations', 'tolerance', 'scale', 'beta', 'lam', 'landmarks',
              'max_points', 'seed', 'normalise', 'priors', 'alpha', 'refine_points',
              'fine_iterations', 'sigma2', 'knn', 'sparse_points', 'sparse_iterations',
              'sparse_knn', 'inlier_threshold'}
GA_PARAMS = {'max_iterations', 'tolerance', 'eps', 'dt', 'damping', 'max_points', 'priors',
             'prior_mass', 'seed', 'polish_trim', 'inlier_threshold'}
BHRGA_PARAMS = {'eps_start', 'eps_end', 'stages', 'theta', 'max_particles', 'iterations',
                'priors', 'prior_mass', 'polish_trim', 'polish_points', 'seed',
                'inlier_threshold'}
NRGA_PARAMS = {'k', 'iterations', 'dt', 'damping', 'beta', 'lam', 'eps_start', 'eps_end',
               'max_points', 'landmarks', 'seed', 'inlier_threshold'}


def register(source: np.ndarray, target: np.ndarray, method: str = 'icp', **params: Any
             ) -> RegistrationResult:
    """Register ``source`` (N, 3) onto ``target`` (M, 3) by method name (see METHODS)."""
    if method in ICP_METHODS:
        unknown = set(params) - ICP_PARAMS
        if unknown:
            raise ValueError(f'{method}: unknown parameter(s) {sorted(unknown)}')
        return icp(source, target, method=ICP_METHODS[method], **params)
    if method in CPD_METHODS:
        unknown = set(params) - CPD_PARAMS
        if unknown:
            raise ValueError(f'{method}: unknown parameter(s) {sorted(unknown)}')
        if method.startswith('ecpd') and params.get('priors') is None:
            raise ValueError(f'{method}: needs priors, (K, 2) pairs (source index, target '
                             'index) of known correspondences')
        return cpd(source, target, kind=CPD_METHODS[method], **params)
    if method == 'ga':
        unknown = set(params) - GA_PARAMS
        if unknown:
            raise ValueError(f'{method}: unknown parameter(s) {sorted(unknown)}')
        return ga(source, target, **params)
    if method == 'bhrga':
        unknown = set(params) - BHRGA_PARAMS
        if unknown:
            raise ValueError(f'{method}: unknown parameter(s) {sorted(unknown)}')
        return bhrga(source, target, **params)
    if method == 'nrga':
        unknown = set(params) - NRGA_PARAMS
        if unknown:
            raise ValueError(f'{method}: unknown parameter(s) {sorted(unknown)}')
        return nrga(source, target, **params)
    raise ValueError(f'method={method!r}: expected one of {METHODS}')


__all__ = ['CPD_METHODS', 'ICP_METHODS', 'METHODS', 'PARAM_RULES', 'GlobalPose',
           'RegistrationResult', 'bhrga', 'check_param', 'cpd', 'ga', 'global_pose', 'icp',
           'nrga', 'register', 'robust_residual']
