"""Griffe extensions for this site: the installed package layout, and the docstrings' markup.

* :class:`PackageDir`: ``pyproject.toml`` installs the top-level ``envs/`` and ``agents/``
  directories as ``smcd_rl.envs`` and ``smcd_rl.agents`` (setuptools ``package-dir``). Griffe finds
  a package's submodules by walking its directory, so it never sees them under ``smcd_rl``. This
  extension loads each mapped directory once the package is loaded and attaches it as the
  submodule its import name says, so ``::: smcd_rl.envs.two_link_arm`` and cross-references to it
  resolve from the source, exactly as for the modules inside ``smcd_rl/``.
* :class:`DocstringMarkup`: the docstrings are Google style with two habits griffe does not read.
  An ``Example:`` section (Google's and napoleon's singular) becomes ``Examples:``, so its ``>>>``
  lines render as code; a Sphinx role such as ``:class:`~smcd_rl.SMCD``` becomes an optional
  cross-reference: a link where the target is documented on this site, plain code where it is not.

Configured in ``mkdocs.yml``, in this order::

    extensions:
      - docs/griffe_extensions.py:PackageDir:
          package: smcd_rl
          mapping: {envs: envs, agents: agents}
      - docs/griffe_extensions.py:DocstringMarkup
"""

from __future__ import annotations

import html
import re
from pathlib import Path
from typing import Any

import griffe

_EXAMPLE = re.compile(r"^(?P<indent>[ \t]*)Example:[ \t]*$", re.MULTILINE)
_ROLE = re.compile(
    r":(?P<role>class|func|meth|attr|data|mod|exc|obj|const|pep):`(?P<target>[^`]+)`"
)


class PackageDir(griffe.Extension):
    """Attach directories outside a package as its submodules (setuptools ``package-dir``).

    Args:
        package: the top-level package the directories belong to.
        mapping: submodule name -> directory, relative to the directory that holds the package.
    """

    def __init__(self, package: str, mapping: dict[str, str]) -> None:
        super().__init__()
        self.package = package
        self.mapping = dict(mapping)

    def on_package(
        self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any
    ) -> None:
        if pkg.name != self.package or pkg.parent is not None:
            return
        root = Path(pkg.filepath).parent.parent  # a package, not a namespace package
        for name, directory in self.mapping.items():
            if name in pkg.members and pkg.members[name].is_module:
                continue
            module = loader.load(root / directory, try_relative_path=True)
            # The loader registered it as a top-level module of its directory's name; it is not one.
            loader.modules_collection.members.pop(module.name, None)
            module.name = name
            pkg.set_member(name, module)


class DocstringMarkup(griffe.Extension):
    """Read ``Example:`` sections as examples and Sphinx roles as optional cross-references."""

    def on_package(
        self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any
    ) -> None:
        _rewrite(pkg)


def _rewrite(obj: griffe.Object) -> None:
    if obj.docstring is not None:
        value = _EXAMPLE.sub(r"\g<indent>Examples:", obj.docstring.value)
        obj.docstring.value = _ROLE.sub(lambda match: _reference(obj, match), value)
    for member in obj.members.values():
        if not member.is_alias:
            _rewrite(member)


def _reference(obj: griffe.Object, match: re.Match[str]) -> str:
    role, target = match["role"], match["target"].strip()
    if role == "pep":
        return f"[PEP {target}](https://peps.python.org/pep-{int(target):04d}/)"
    short = target.startswith("~")
    target = target.lstrip("~.")
    title = target.rsplit(".", 1)[-1] if short else target
    head, _, rest = target.partition(".")
    try:
        identifier = obj.resolve(head) + ("." + rest if rest else "")
    except (
        Exception
    ):  # not a name in this scope (e.g. torch.save): keep it, the reference is optional
        identifier = target
    return (
        f'<autoref identifier="{html.escape(identifier)}" optional>`{title}`</autoref>'
    )
