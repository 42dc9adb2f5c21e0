"""Command-line options shared by ``kf-train replay`` and ``kf-train compare``: the tuning."""

import argparse
import math

from kf_train.filters import (
    DEFAULT_ALPHA, DEFAULT_BETA, DEFAULT_KAPPA, DEFAULT_PARTICLES, DEFAULT_RESAMPLE_THRESHOLD,
    FilterOptions, MAX_PARTICLES)


def add_filter_options(parser: argparse.ArgumentParser) -> None:
    """Add the tuning options: UKF --alpha/--beta/--kappa, PF --particles/--seed/...."""
    group = parser.add_argument_group('filter tuning (ukf: alpha, beta, kappa; pf: the rest)')
    group.add_argument('--alpha', type=float, default=DEFAULT_ALPHA,
                       help='UKF sigma-point spread alpha > 0 (default %(default)g)')
    group.add_argument('--beta', type=float, default=DEFAULT_BETA,
                       help='UKF beta (default %(default)g, optimal for Gaussians)')
    group.add_argument('--kappa', type=float, default=DEFAULT_KAPPA,
                       help='UKF kappa, n + kappa > 0 (default %(default)g)')
    group.add_argument('--particles', metavar='N', type=int, default=DEFAULT_PARTICLES,
                       help='particle filter: number of particles (default %(default)d)')
    group.add_argument('--seed', metavar='S', type=int, default=0,
                       help='random seed (default %(default)d)')
    group.add_argument('--resample-threshold', metavar='F', type=float,
                       default=DEFAULT_RESAMPLE_THRESHOLD,
                       help='particle filter: resample when ESS < F·N (default %(default)g)')
    group.add_argument('--roughening', metavar='K', type=float, default=0.0,
                       help='particle filter: after resampling, jitter each state by '
                            'N(0, (K·range·N^(-1/n))²) (Gordon et al. 1993); 0, the '
                            'default, is the plain bootstrap filter')


def filter_options(args: argparse.Namespace) -> FilterOptions:
    """Return the checked FilterOptions parsed by :func:`add_filter_options`."""
    options = FilterOptions(alpha=args.alpha, beta=args.beta, kappa=args.kappa,
                            particles=args.particles, seed=args.seed,
                            resample_threshold=args.resample_threshold,
                            roughening=args.roughening)
    if not 1 <= options.particles <= MAX_PARTICLES:
        raise ValueError(f'--particles must be in [1, {MAX_PARTICLES}], got {options.particles}')
    if options.seed < 0:
        raise ValueError(f'--seed must be >= 0, got {options.seed}')
    if not 0.0 <= options.resample_threshold <= 1.0:
        raise ValueError(f'--resample-threshold must be in [0, 1], got '
                         f'{options.resample_threshold}')
    if not 0.0 <= options.roughening < math.inf:
        raise ValueError(f'--roughening must be a finite number >= 0, got '
                         f'{options.roughening}')
    for name in ('alpha', 'beta', 'kappa'):
        if not math.isfinite(getattr(options, name)):
            raise ValueError(f'--{name} must be a finite number, got {getattr(options, name)}')
    if options.alpha <= 0.0:
        raise ValueError(f'--alpha must be > 0, got {options.alpha}')
    return options  # n + kappa > 0 is checked by make_filter, which knows n
