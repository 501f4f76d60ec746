"""Check a freshly bootstrapped environment before ``./run`` marks it ready.

Usage::

    VENV/bin/python tools/check_bootstrap.py ROOT VENV [--constraints FILE] [--no-rclpy]

Exit status 0 when every ``console_scripts`` entry of ``ROOT/setup.py`` is an executable
file in ``VENV/bin`` (the folder ``./run`` puts first on PATH) and ``rclpy``,
``gnsscam_ros`` and ``msg_adapters`` import, the last two from ``ROOT`` (the development
install); 1 otherwise, with one line per problem on stderr. Standard library only: it runs
before anything of the project is known to work.

A platform tier (``./run test --tier NAME``) also passes its constraints file: every
``name==version`` pin must be the installed version, and every ``# import: module==version``
line (a package without pip metadata, such as Debian's python3-opencv) the module's
``__version__``. ``--no-rclpy`` is for a tier without ROS 2 (no rclpy, so no msg_adapters,
whose messages come from ROS).

Why: pip's legacy ``setup.py develop`` (pip < 23.1, or any pip when ``wheel`` is
installed and the project has no pyproject.toml) obeys ``setup.cfg [develop] script_dir``,
which ament/colcon need and which puts the scripts in ``lib/gnsscam_ros`` instead of
``bin`` (Debian's python3.11 with pip 23.0.1 did exactly that).
"""
from __future__ import annotations

import ast
import importlib
import importlib.metadata
import os
import re
import sys
from pathlib import Path

MODULES = ('rclpy', 'gnsscam_ros', 'msg_adapters')
#: What a tier without ROS 2 (``--no-rclpy``) must import.
MODULES_WITHOUT_ROS = ('gnsscam_ros',)
#: ``name==version`` (a pin) and ``# import: module==version`` lines of a constraints file.
_PIN = re.compile(r'^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)\s*$')
_IMPORT_PIN = re.compile(r'^#\s*import:\s*([A-Za-z_][\w.]*)==(\S+)\s*$')
#: Modules that must come from the source tree (development install).
FROM_ROOT = ('gnsscam_ros', 'msg_adapters')


class SetupError(ValueError):
    """setup.py does not declare its console scripts in a form this check can read."""


def console_scripts(setup_py: str | os.PathLike) -> list[str]:
    """Executable names of ``entry_points={'console_scripts': [...]}`` in a setup.py.

    Read without running setup.py (literal values only).

    Raises:
        SetupError: No literal ``console_scripts`` list, or an entry without ``=``.
    """
    path = Path(setup_py)
    tree = ast.parse(path.read_text(encoding='utf-8'), filename=str(path))
    for node in ast.walk(tree):
        if not (isinstance(node, ast.keyword) and node.arg == 'entry_points'):
            continue
        try:
            entry_points = ast.literal_eval(node.value)
        except ValueError as err:
            raise SetupError(f'{path}: entry_points is not a literal') from err
        entries = entry_points.get('console_scripts', [])
        names = []
        for entry in entries:
            name, sep, _ = entry.partition('=')
            if not sep or not name.strip():
                raise SetupError(f'{path}: console_scripts entry {entry!r} has no name =')
            names.append(name.strip())
        return names
    raise SetupError(f'{path}: no entry_points keyword')


def missing_scripts(names: list[str], bin_dir: str | os.PathLike) -> list[str]:
    """Problems with the console scripts: not in ``bin_dir`` or not executable."""
    out = []
    for name in names:
        path = Path(bin_dir) / name
        if not path.is_file():
            out.append(f'console script {name} is not in {bin_dir}')
        elif not os.access(path, os.X_OK):
            out.append(f'console script {path} is not executable')
    return out


def import_problems(root: str | os.PathLike, modules=MODULES, from_root=FROM_ROOT
                    ) -> list[str]:
    """Problems importing ``modules`` (and ``from_root`` ones living outside ``root``)."""
    out = []
    root = Path(root).resolve()
    for name in modules:
        try:
            module = importlib.import_module(name)
        except Exception as err:          # report every failure, whatever its kind
            out.append(f'import {name} failed: {type(err).__name__}: {err}')
            continue
        where = getattr(module, '__file__', None)
        if name in from_root and (where is None
                                  or root not in Path(where).resolve().parents):
            out.append(f'{name} is imported from {where}, not from {root} (the development '
                       'install is missing or shadowed)')
    return out


def read_pins(constraints: str | os.PathLike) -> tuple[dict, dict]:
    """The pins of a constraints file: ``({distribution: version}, {module: version})``."""
    dists, modules = {}, {}
    for line in Path(constraints).read_text(encoding='utf-8').splitlines():
        line = line.strip()
        if match := _PIN.match(line):
            dists[match.group(1)] = match.group(2)
        elif match := _IMPORT_PIN.match(line):
            modules[match.group(1)] = match.group(2)
    return dists, modules


def version_problems(dists: dict, modules: dict) -> list[str]:
    """Installed versions that are not the pinned ones (see :func:`read_pins`)."""
    out = []
    for name, want in dists.items():
        try:
            have = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out.append(f'{name}=={want} is pinned but not installed')
            continue
        if have != want:
            out.append(f'{name} is {have}, pinned to {want}')
    for name, want in modules.items():
        try:
            have = getattr(importlib.import_module(name), '__version__', None)
        except Exception as err:          # report every failure, whatever its kind
            out.append(f'import {name} failed: {type(err).__name__}: {err}')
            continue
        if have != want:
            out.append(f'{name}.__version__ is {have}, pinned to {want}')
    return out


def check(root: str | os.PathLike, venv: str | os.PathLike,
          constraints: str | os.PathLike | None = None, ros: bool = True) -> list[str]:
    """Every problem of the environment ``venv`` for the source tree ``root``.

    Args:
        root: The source tree.
        venv: The environment.
        constraints: A tier's constraints file, whose pins must be what is installed.
        ros: Whether rclpy (and msg_adapters, which needs ROS messages) must import.
    """
    try:
        names = console_scripts(Path(root) / 'setup.py')
    except (OSError, SyntaxError, SetupError) as err:
        return [f'cannot read the console scripts: {err}']
    problems = missing_scripts(names, Path(venv) / 'bin') + import_problems(
        root, modules=MODULES if ros else MODULES_WITHOUT_ROS)
    if constraints is not None:
        try:
            problems += version_problems(*read_pins(constraints))
        except OSError as err:
            problems.append(f'cannot read the constraints: {err}')
    return problems


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    ros = '--no-rclpy' not in args
    args = [a for a in args if a != '--no-rclpy']
    constraints = None
    if '--constraints' in args:
        at = args.index('--constraints')
        constraints = args[at + 1] if at + 1 < len(args) else None
        del args[at:at + 2]
        if constraints is None:
            args = []                     # --constraints without a file: usage
    if len(args) != 2:
        print('usage: check_bootstrap.py ROOT VENV [--constraints FILE] [--no-rclpy]',
              file=sys.stderr)
        return 2
    problems = check(*args, constraints=constraints, ros=ros)
    for line in problems:
        print(f'[run] bootstrap check: {line}', file=sys.stderr)
    return 1 if problems else 0


if __name__ == '__main__':
    sys.exit(main())
