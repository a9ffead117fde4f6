/**
 * The task's rules in the browser: the grid, non-penetration and support.
 *
 * A tower is a list of blocks `[width, x, layer]`, the ground block first. A block in layer L has
 * its bottom at `L * block_height`. These checks give the participant feedback while they move the
 * preview; the server decides what counts.
 */

export const DEFAULT_GRID = Object.freeze({ half_width: 4, height: 8, block_height: 0.6, max_layer: 12 });

const EPS = 1e-9;

export function overlapLength(left1, right1, left2, right2) {
  return Math.min(right1, right2) - Math.max(left1, left2);
}

/** Why a block of `width` cannot go to (x, layer) on `tower`, or null when it can. */
export function illegalReason(tower, width, x, layer, grid = DEFAULT_GRID) {
  const left = x - width / 2;
  const right = x + width / 2;
  if (left < -grid.half_width - EPS || right > grid.half_width + EPS) {
    return "The block would stick out of the grid.";
  }
  if (!Number.isInteger(layer) || layer < 0 || layer > grid.max_layer) {
    return "That layer is outside the grid.";
  }
  if (layer === 0) {
    return "Only the first block stands on the ground.";
  }
  let support = 0;
  for (const [w, bx, bl] of tower) {
    const overlap = overlapLength(left, right, bx - w / 2, bx + w / 2);
    if (bl === layer && overlap > EPS) {
      return "The block would overlap a block of the same layer.";
    }
    if (bl === layer - 1) {
      support = Math.max(support, overlap);
    }
  }
  if (support <= EPS) {
    return "The block must rest on a block in the layer below.";
  }
  return null;
}

export function isLegal(tower, width, x, layer, grid = DEFAULT_GRID) {
  return illegalReason(tower, width, x, layer, grid) === null;
}

/** The largest horizontal reach of the tower from x = 0: max |x| + width / 2. */
export function overhang(tower) {
  return tower.reduce((best, [w, x]) => Math.max(best, Math.abs(x) + w / 2), 0);
}

/** The tower at rest as poses `[x, z, angle]`, z the height of each block's centre. */
export function restingPoses(tower, grid = DEFAULT_GRID) {
  return tower.map(([, x, layer]) => [x, (layer + 0.5) * grid.block_height, 0]);
}

/**
 * Where the preview of a block of `width` goes for a pointer at task coordinates {x, z}: x kept
 * inside the grid and rounded to 0.001, the layer under the pointer; null above the grid.
 */
export function previewPosition(point, width, grid = DEFAULT_GRID) {
  if (!point || point.z > grid.height) return null;
  const limit = grid.half_width - width / 2;
  const x = Math.round(Math.min(limit, Math.max(-limit, point.x)) * 1000) / 1000;
  const layer = Math.min(grid.max_layer, Math.max(0, Math.floor(point.z / grid.block_height)));
  return { x, layer };
}

export function groundTower(sequence) {
  return [[sequence[0], 0, 0]];
}
