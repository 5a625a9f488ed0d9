"""Shared helpers of the widgets: lazy ipywidgets, redrawing a figure into an Output."""

from __future__ import annotations

from ..errors import OrganlabError


def ipywidgets():
    """The ipywidgets module, imported on first use."""
    try:
        import ipywidgets as w
    except ImportError:  # pragma: no cover - ipywidgets is in environment.txt
        raise OrganlabError("organlab.widgets needs ipywidgets: pip install ipywidgets") from None
    return w


def new_figure(width_in, height_in):
    """A matplotlib Figure not registered with pyplot (no global state, shown once by Jupyter)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout="constrained")


def redraw(output, make_figure):
    """Replace the content of an ipywidgets Output with ``make_figure()``; errors become a line of text.

    Returns the figure drawn (None after an error).
    """
    from IPython.display import display

    fig = None
    with output:
        output.clear_output(wait=True)
        try:
            fig = make_figure()
            display(fig)
        except (OrganlabError, ValueError) as e:
            print(f"error: {e}")
    return fig
