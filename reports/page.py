"""What every page shares: escaping user text and the head of a self-contained HTML file."""

from __future__ import annotations

import html


def esc(value: object) -> str:
    """Escape any user-supplied value for HTML text or a quoted attribute."""
    return html.escape(str(value), quote=True)


def scroll_open(label: str, hidden: bool = False) -> str:
    """The opening tag of a box that scrolls its table sideways: focusable, as keyboards scroll
    only what they can focus (only Chromium 130+ focuses a scroller by itself), and a region
    named `label` (its table), which is how screen readers announce the stop. Every box gets
    them: whether it scrolls depends on the reader's screen, which is not known here. A box
    filled later starts `hidden`, not an empty Tab stop."""
    return (f'<div class="scroll" tabindex="0" role="region" aria-label="{esc(label)}"'
            f'{" hidden" if hidden else ""}>')


def head(title: str, csp: str, css: str) -> str:
    """From the doctype to </head>: UTF-8, the Content-Security-Policy, the inline style."""
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="{csp}">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>{css}</style>
</head>"""
