"""What every reconstruction method supplies (docs/design.md section 3).

A method is an object, chosen once where a string option is read
(`mi_amr.reconstruction.reconstruction_method`); the structures, samplers and
oracles ask the object what they need and never its name (OpenVKL's AMR
volume: one sampler per method, ``method_current`` / ``finest`` / ``octant``).
A method has no per-lane state of its own: its device parts are Python code
that the symbolic loops of `mi_amr.device` run while they are recorded, so a
different method is a different kernel, never a branch inside one.

Parts of a method, by the layer that asks:

* **Support**: ``support_radius`` ``r`` (half-width of a cell's support, in
  cell widths) and `Reconstruction.support_box`, the one formula for the box
  ``[c - r w, c + r w]`` that the macrocell ranges, the region-tree ranges
  and the value masks splat.
* **Data**: ``needs_ghosts`` (the point-location hash also holds ghost
  blocks and neighbour rows, which the block size choice weighs) and
  ``hash_bytes_per_block`` (`mi_amr.memory.hash_bytes`).
* **Host**: `brute_force_chunk` (the O(cells) test oracle,
  `mi_amr.testing.brute_force`) and `host_eval` (numpy over the blocks,
  `mi_amr.structures.host_reconstruction`).
* **Value masks**: ``value_masks_tighten`` (whether masks can lower the
  majorants at all), `mask_items` and `mask_item_box`
  (`mi_amr.structures.value_masks`).
* **Device, hash** (`mi_amr.device.hash_sampler.DeviceReconstruction.eval`):
  the loop state, the probe order (`hash_level`), the body of one loop
  iteration at one level (`hash_step`), an early exit (`hash_stop`) and the
  result.
* **Device, bricks** (`mi_amr.device.bricks.BrickSampler.eval_at`): the loop
  state, one brick's contribution (`brick_step`) and the result.
* **References**: ``grid_filter`` and ``dense_exact``
  (`mi_amr.reference`, the ``dense16`` benchmark).
"""

from __future__ import annotations

#: Where the tent weights at a point sum to at most this, there is no value.
WEIGHT_EPS = 1e-20


class Reconstruction:
    """Base of the reconstruction methods; see the module docstring. A
    method is stateless: two objects of one class are equal."""

    #: The option value (``reconstruction="..."``): what options, to_string
    #: and the command line print.
    name: str = ""
    #: Half-width of a cell's support in cell widths: a cell of centre ``c``
    #: and width ``w`` contributes to ``f(x)`` only where every ``|x_k - c_k|
    #: <= r w``. A multiple of 1/2 (the region trees count in half cells).
    support_radius: float = 0.5
    #: The point-location hash holds ghost blocks and neighbour rows too
    #: (`mi_amr.data.blocks.BlockVolume.stencil_index`).
    needs_ghosts: bool = False
    #: Per-macrocell value masks can give a lower majorant than the value
    #: range (docs/design.md section 4).
    value_masks_tighten: bool = False
    #: Peak host bytes per data block of building the point-location hash
    #: (keys, payload, build rounds, and what ``needs_ghosts`` adds), without
    #: the device copy of the values; measured with tracemalloc.
    hash_bytes_per_block: float = 0.0
    #: ``filter_type`` of Mitsuba's ``gridvolume`` that gives this field from
    #: a dense resampling at voxel centres (`mi_amr.reference`).
    grid_filter: str = ""
    #: Whether that resampling at the finest resolution is this field
    #: exactly, for any data and TF.
    dense_exact: bool = False

    def __str__(self) -> str:
        return self.name

    def __repr__(self) -> str:
        return f"reconstruction_method({self.name!r})"

    def __eq__(self, other) -> bool:
        return type(other) is type(self)

    def __hash__(self) -> int:
        return hash(type(self))

    # ---- Support -------------------------------------------------------
    @property
    def support_beyond_cell(self) -> bool:
        """A cell's support reaches past its own box (into the cells and
        bricks around it)."""
        return self.support_radius > 0.5

    def support_box(self, lo, w):
        """Support ``[c - r w, c + r w]`` along an axis of cells with lower
        corners ``lo`` and widths ``w`` (``c = lo + w / 2``; numpy arrays or
        floats, broadcast). Written from the lower corner, so that integer
        corners and power-of-two widths give exact bounds."""
        r = self.support_radius
        return lo + (0.5 - r) * w, lo + (0.5 + r) * w

    # ---- Host ----------------------------------------------------------
    def brute_force_chunk(self, lo, w, value, x):
        """``(value, found)`` at points ``x`` (m, 1, 3) from every cell: lower
        corners ``lo`` (n, 3), widths ``w`` (n,), values (n,); float64."""
        raise NotImplementedError

    def host_eval(self, volume, x):
        """``(value, found)`` at points ``x`` (M, 3), float64 finest units
        relative to ``volume.origin``, through `BlockVolume.lookup`."""
        raise NotImplementedError

    # ---- Value masks ---------------------------------------------------
    def mask_items(self, volume, bins):
        """Yield ``(level (k,), coord (k, 3), work)`` per chunk of blocks:
        ``work()`` (called in a worker thread) returns the value bins of the
        item based at each cell of each block ((k, B, B, B) uint64, indexed
        [block, z, y, x]) and the cells read."""
        raise NotImplementedError

    def mask_item_box(self, q, w):
        """Lower and upper bound along one axis (finest units from the
        origin) of the region where the item based at level coordinate
        ``q`` (any shape) of width-``w`` cells gives the field's values."""
        raise NotImplementedError

    # ---- Device: hash of blocks ----------------------------------------
    def hash_state(self, cells):
        """The loop state this method adds to the hash look-up loop (a
        tuple of Dr.Jit arrays, each changed by every iteration).
        ``cells`` (`mi_amr.data.device_values.CellValues`) gathers the values:
        a ``Float``, or a ``Vector2f`` when a second field is carried."""
        raise NotImplementedError

    def hash_level(self, remaining):
        """The level to probe next among the bits of ``remaining``."""
        raise NotImplementedError

    def hash_step(self, table, cells, L, xl, fl, limit, probe, state):
        """One loop iteration at level ``L``: ``xl`` the point in level
        units, ``fl = floor(xl)``, ``limit`` the largest level coordinate
        the hash holds, ``probe`` the linear-probing step. Returns
        ``(level_done, probe, state)``."""
        raise NotImplementedError

    def hash_stop(self, remaining, state):
        """``remaining`` after an iteration: levels still to visit."""
        return remaining

    def hash_result(self, state):
        """``(value, found)`` after the loop."""
        raise NotImplementedError

    # ---- Device: bricks ------------------------------------------------
    def brick_state(self, cells):
        """The loop state this method adds to the brick list loop."""
        raise NotImplementedError

    def brick_step(self, bricks, cells, b, x, active, state, over_bounds, in_domain):
        """Fold brick ``b`` of `DeviceBricks` ``bricks`` at point ``x`` into
        ``state``. ``over_bounds``: the list is the one brick whose bounds
        hold the whole leaf (``in_domain``: the point is in the data)."""
        raise NotImplementedError

    def brick_result(self, state):
        """``(value, found)`` after the loop."""
        raise NotImplementedError
