"""A griffe extension for the API reference (mkdocs.yml, mkdocstrings' python handler).

The docstrings are Markdown, written as plain text reads: a list follows its lead-in line
directly (`**Arguments:**` then `- name: ...`). Python-Markdown starts a list only after a
blank line, and would run such a list into the paragraph before it. This extension puts
a blank line before the first item of every such list (outside code blocks and fences);
nothing else in the docstring changes.
"""

from __future__ import annotations

import re

import griffe

ITEM = re.compile(r"([-*+]|\d+[.)])\s")


def blank_line_before_lists(text: str) -> str:
    out: list[str] = []
    in_list = in_code = in_fence = False
    previous_blank = True
    for line in text.split("\n"):
        stripped = line.lstrip()
        indent = len(line) - len(stripped)
        if stripped.startswith(("```", "~~~")):
            in_fence = not in_fence
        elif in_fence:
            pass
        elif not stripped:
            previous_blank = True
            out.append(line)
            continue
        elif in_code and indent >= 4:
            pass  # an indented code block goes on
        elif previous_blank and indent >= 4 and not in_list:
            in_code = True  # an indented code block (an equation) starts
        else:
            in_code = False
            if ITEM.match(stripped) and (indent < 4 or in_list):
                if not previous_blank and not in_list:
                    out.append("")
                in_list = True
            elif previous_blank and indent == 0:
                in_list = False  # a new paragraph
        previous_blank = False
        out.append(line)
    return "\n".join(out)


class BlankLineBeforeLists(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = blank_line_before_lists(obj.docstring.value)
