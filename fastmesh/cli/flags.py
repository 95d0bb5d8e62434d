"""The generation parameters as command-line flags, made from :data:`fastmesh.params.PARAMETERS`.

``generate``, ``eval``, ``submit`` and ``loadtest`` take their flags from here: a parameter declared in
``GenerateParams`` is a flag of each (``--top-k`` for ``top_k``; a bool as ``--uv`` / ``--no-uv``), with the
type, default, values and help the declaration gives.
"""

from __future__ import annotations

import argparse

from fastmesh.params import PARAMETERS, GenerateParams, Parameter


def _help(prm: Parameter, defaults: bool) -> str:
    """The flag's help: what the parameter does, then its default."""
    text = prm.help.replace("%", "%%")  # argparse formats help with %
    if not defaults:
        return f"{text} (default: the server's)"
    if prm.default is None:
        return f"{text} (default: {prm.unset})" if prm.unset else text
    return f"{text} (default: %(default)s)"


def add_param_flags(p: argparse.ArgumentParser, defaults: bool = True, output: bool | None = None) -> None:
    """Add one flag per generation parameter to ``p``.

    Parameters
    ----------
    p : argparse.ArgumentParser
        The command's parser.
    defaults : bool
        The flags default to ``GenerateParams``' values; without, an unset flag is None (a service's default).
    output : bool or None
        Only the parameters of the written result (True), only the others (False), or all of them (None).
    """
    for prm in PARAMETERS:
        if output is not None and prm.output != output:
            continue
        kw = {"default": prm.default if defaults else None, "help": _help(prm, defaults)}
        if prm.type is bool:
            kw["action"] = argparse.BooleanOptionalAction
        elif prm.choices:
            kw["choices"] = prm.choices
        else:
            kw.update(type=prm.type, metavar=prm.metavar)
        p.add_argument(prm.flag, dest=prm.name, **kw)


def params_from_args(args: argparse.Namespace) -> GenerateParams:
    """The ``GenerateParams`` of parsed flags; a parameter the command has no flag for keeps its default."""
    return GenerateParams(**{prm.name: getattr(args, prm.name) for prm in PARAMETERS if hasattr(args, prm.name)})


def given_params(args: argparse.Namespace) -> dict:
    """The parameters set on the command line of a command made with ``defaults=False`` (None: left to the
    service)."""
    return {prm.name: getattr(args, prm.name) for prm in PARAMETERS
            if hasattr(args, prm.name) and getattr(args, prm.name) is not None}
