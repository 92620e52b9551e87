"""An interactive 3-D view of a trajectory in Jupyter: :func:`show`, through nglview.

nglview is an optional dependency (``pip install "leapmd[notebook]"`` or
``pip install nglview``); without it :func:`show` says what to install.
"""

from __future__ import annotations

import importlib
import io
import os
import warnings

from md.trajectory import open_trajectory

INSTALL_HINT = (
    "md.show needs nglview, an optional dependency: pip install 'leapmd[notebook]' "
    "(or pip install nglview), then restart the notebook's kernel"
)


def show(path_or_universe, **kwargs):
    """Return an nglview widget showing a trajectory (bonds included), for a notebook cell.

    Parameters
    ----------
    path_or_universe : path or MDAnalysis.Universe
        An H5MD file written by leapmd (opened with :func:`md.open_trajectory`,
        so types and bonds come along) or a Universe already open.
    **kwargs
        Passed to ``nglview.show_mdanalysis``.

    Raises
    ------
    ImportError
        If nglview is not installed; the message says how to install it.
    TrajectoryError
        If the path is not a trajectory of ours.
    """
    try:
        nglview = importlib.import_module("nglview")  # optional: md.show only
    except ImportError:
        raise ImportError(INSTALL_HINT) from None
    if isinstance(path_or_universe, str | os.PathLike):
        universe = open_trajectory(path_or_universe)
    else:
        universe = path_or_universe
    return nglview.NGLWidget(_with_bonds(nglview, universe), **kwargs)


def _with_bonds(nglview, universe):
    """nglview's MDAnalysis adaptor, but writing every bond as a PDB CONECT record.

    The stock adaptor writes only CONECT records read from a PDB file, so a
    polymer melt would show as loose beads (or as bonds NGL guesses from
    distances).
    """
    import MDAnalysis as mda  # heavy: with nglview, on first use

    class BondedTrajectory(nglview.MDAnalysisTrajectory):
        def get_structure_string(self):
            self.atomgroup.universe.trajectory[0]
            stream = mda.lib.util.NamedStream(io.StringIO(), "structure.pdb")
            atoms = self.atomgroup.atoms
            # MDAnalysis: a Universe has a bonds attribute only when its topology lists bonds
            bonds = "all" if hasattr(atoms.universe, "bonds") else None
            with mda.Writer(stream, atoms.n_atoms, multiframe=False, bonds=bonds) as writer:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # PDB's missing attributes, guessed
                    writer.write(atoms)
            return stream.read()

    return BondedTrajectory(universe)


__all__ = ["INSTALL_HINT", "show"]
