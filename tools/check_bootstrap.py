"""Check a freshly bootstrapped environment before ``./run`` marks it ready.

Usage::

    VENV/bin/python tools/check_bootstrap.py ROOT VENV

Exit status 0 when every ``console_scripts`` entry of ``ROOT/setup.py`` is an executable
file in ``VENV/bin`` (the folder ``./run`` puts first on PATH) and ``rclpy``,
``gnsscam_ros`` and ``msg_adapters`` import, the last two from ``ROOT`` (the development
install); 1 otherwise, with one line per problem on stderr. Standard library only: it runs
before anything of the project is known to work.

Why: pip's legacy ``setup.py develop`` (pip < 23.1, or any pip when ``wheel`` is
installed and the project has no pyproject.toml) obeys ``setup.cfg [develop] script_dir``,
which ament/colcon need and which puts the scripts in ``lib/gnsscam_ros`` instead of
``bin`` (Debian's python3.11 with pip 23.0.1 did exactly that).
"""
from __future__ import annotations

import ast
import importlib
import os
import sys
from pathlib import Path

MODULES = ('rclpy', 'gnsscam_ros', 'msg_adapters')
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


def check(root: str | os.PathLike, venv: str | os.PathLike) -> list[str]:
    """Every problem of the environment ``venv`` for the source tree ``root``."""
    try:
        names = console_scripts(Path(root) / 'setup.py')
    except (OSError, SyntaxError, SetupError) as err:
        return [f'cannot read the console scripts: {err}']
    return missing_scripts(names, Path(venv) / 'bin') + import_problems(root)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print('usage: check_bootstrap.py ROOT VENV', file=sys.stderr)
        return 2
    problems = check(*args)
    for line in problems:
        print(f'[run] bootstrap check: {line}', file=sys.stderr)
    return 1 if problems else 0


if __name__ == '__main__':
    sys.exit(main())
