"""What every page shares: escaping user text and the head of a self-contained HTML file."""

from __future__ import annotations

import html


def esc(value: object) -> str:
    """Escape any user-supplied value for HTML text or a quoted attribute."""
    return html.escape(str(value), quote=True)


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
