"""`pma plot BAG [-o FILE.png] [--show]`: the bag's figure (pma_model.offline.bag_plot), no ROS
graph."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pma_cli.session import FAILED, USAGE

# Tried in this order for --show: matplotlib's interactive backends.
INTERACTIVE_BACKENDS = ('QtAgg', 'TkAgg', 'GTK4Agg', 'GTK3Agg', 'wxAgg', 'macosx')


def has_display() -> bool:
    return sys.platform in ('darwin', 'win32') or bool(
        os.environ.get('DISPLAY') or os.environ.get('WAYLAND_DISPLAY'))


def show(path: Path) -> str:
    """Open the written PNG in a matplotlib window; '' when shown, else why not."""
    if not has_display():
        return 'no display (neither DISPLAY nor WAYLAND_DISPLAY is set)'
    import matplotlib.pyplot as plt
    for backend in INTERACTIVE_BACKENDS:
        try:
            plt.switch_backend(backend)
        except (ImportError, RuntimeError, ValueError):
            continue
        figure = plt.figure(figsize=(13, 7.5))
        figure.figimage(plt.imread(path), resize=True)
        figure.canvas.manager.set_window_title(path.name)
        plt.show()
        return ''
    return f'no interactive matplotlib backend could start ({", ".join(INTERACTIVE_BACKENDS)})'


def plot(bag: Path, out: Path | None, topic: str, show_it: bool) -> int:
    if not bag.exists():              # before matplotlib and the model are imported (~2 s)
        print(f'pma plot: {bag}: no such bag', file=sys.stderr)
        return FAILED
    from pma_model.offline.bag_plot import BagPlotError, default_output, plot_bag

    target = out if out is not None else default_output(bag)
    if not target.parent.is_dir():
        print(f'pma plot: there is no directory {target.parent} to write {target.name} in',
              file=sys.stderr)
        return USAGE
    try:
        path, series, _ = plot_bag(bag, target, topic=topic)
    except BagPlotError as error:
        print(f'pma plot: {error}', file=sys.stderr)
        return FAILED
    except OSError as error:
        print(f'pma plot: cannot write {target}: {error.strerror}', file=sys.stderr)
        return FAILED
    decimated = (f', plotted as {series.time_s.size} (min/max of every {series.bucket})'
                 if series.decimated else '')
    print(f'{path}: {series.samples} samples of {series.state_topic} over '
          f'{series.time_s[-1]:.1f} s{decimated}'
          + ('' if series.prediction else '; no pma/prediction in the bag')
          + ('; with the length controller\'s target' if series.control else ''))
    if series.truncated:
        print(f'pma plot: warning: the bag is unfinished or truncated ({series.truncated}); '
              'plotted what it holds so far', file=sys.stderr)
    if show_it:
        why_not = show(path)
        if why_not:
            print(f'pma plot: --show: {why_not}; the figure is in {path}', file=sys.stderr)
    return 0
