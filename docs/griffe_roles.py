"""A griffe extension for the API reference: the docstrings' reST roles as code.

The library's docstrings are prose with Sphinx roles (``:func:`localize```, ``:mod:`.frame```);
the site renders them as Markdown, where a role would show its colons. Each becomes the code
span of its target (``localize``, ``.frame``); the docstrings themselves stay as they are.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|meth|class|mod|attr|data|obj|exc|const):`~?([^`]+)`")


class Roles(griffe.Extension):
    def on_instance(self, *, obj, **kwargs):
        docstring = getattr(obj, "docstring", None)
        if docstring is not None and ":" in docstring.value:
            docstring.value = ROLE.sub(r"`\1`", docstring.value)
