/**
 * Drawing the task on a <canvas>: the grid in the x-z plane, the tower, the preview block and,
 * optionally, the block sequence in a strip above the grid.
 *
 * Task units map to CSS pixels by `pixelsPerUnit`; `originX`/`originY` is the pixel position of
 * (x = 0, z = 0) relative to the canvas's top-left corner, z growing upwards.
 */

import { DEFAULT_GRID } from "./geometry.js";

export const COLORS = Object.freeze({
  background: "#f8fafc",
  gridFill: "#ffffff",
  bandFill: "#f1f5f9",
  gridLine: "#e2e8f0",
  gridBorder: "#94a3b8",
  ground: "#64748b",
  block: "#3b82f6",
  blockEdge: "#1e3a8a",
  placedInSequence: "#cbd5e1",
  placedEdge: "#94a3b8",
  next: "#f59e0b",
  nextEdge: "#92400e",
  legal: "rgba(34, 197, 94, 0.55)",
  legalEdge: "#15803d",
  illegal: "rgba(239, 68, 68, 0.45)",
  illegalEdge: "#b91c1c",
  text: "#334155",
  reach: "#64748b",
});

// Room beside the grid for blocks that fall off it; blocks that land further out are marked at the edge.
const SIDE_MARGIN = 2.0;
const GROUND_DEPTH = 0.4;
const TOP_PADDING = 0.25;
const SEQUENCE_STRIP = 1.4;

/** A pixel scale that fits the scene into the window, between 30 and 72 pixels per unit. */
export function fittingPixelsPerUnit(grid = DEFAULT_GRID, { showSequence = true, reservedHeight = 240 } = {}) {
  const unitsWide = 2 * (grid.half_width + SIDE_MARGIN);
  const unitsHigh = grid.height + GROUND_DEPTH + TOP_PADDING + (showSequence ? SEQUENCE_STRIP : 0);
  const byWidth = (window.innerWidth - 40) / unitsWide;
  const byHeight = (window.innerHeight - reservedHeight) / unitsHigh;
  return Math.max(30, Math.min(72, Math.floor(Math.min(byWidth, byHeight))));
}

export class TowerScene {
  constructor(canvas, { grid = DEFAULT_GRID, pixelsPerUnit = 56, showSequence = true } = {}) {
    this.canvas = canvas;
    this.grid = grid;
    this.ppu = pixelsPerUnit;
    this.showSequence = showSequence;

    const strip = showSequence ? SEQUENCE_STRIP : 0;
    this.width = Math.round(2 * (grid.half_width + SIDE_MARGIN) * this.ppu);
    this.height = Math.round((grid.height + GROUND_DEPTH + TOP_PADDING + strip) * this.ppu);
    this.originX = this.width / 2;
    this.originY = Math.round((grid.height + TOP_PADDING + strip) * this.ppu);

    const ratio = window.devicePixelRatio || 1;
    canvas.width = Math.round(this.width * ratio);
    canvas.height = Math.round(this.height * ratio);
    canvas.style.width = `${this.width}px`;
    canvas.style.height = `${this.height}px`;
    this.ctx = canvas.getContext("2d");
    this.ctx.setTransform(ratio, 0, 0, ratio, 0, 0);

    Object.assign(canvas.dataset, {
      pxPerUnit: String(this.ppu),
      originX: String(this.originX),
      originY: String(this.originY),
      blockHeight: String(grid.block_height),
      halfWidth: String(grid.half_width),
      maxLayer: String(grid.max_layer),
    });
  }

  toPixel(x, z) {
    return [this.originX + x * this.ppu, this.originY - z * this.ppu];
  }

  /** Task coordinates {x, z} of a pointer event's position. */
  toTask(event) {
    const rect = this.canvas.getBoundingClientRect();
    return {
      x: (event.clientX - rect.left - this.originX) / this.ppu,
      z: (this.originY - (event.clientY - rect.top)) / this.ppu,
    };
  }

  /**
   * Draws a frame of the scene.
   *  - blocks: `[width, x, z, angle]` per block (z the centre's height, angle counter-clockwise);
   *  - ghost: `{width, x, layer, legal}` or null;
   *  - sequence: the block widths; `placed` of them are placed, and `next` (or null) is highlighted.
   */
  draw({ blocks = [], ghost = null, sequence = null, placed = 0, next = null } = {}) {
    const { ctx } = this;
    ctx.clearRect(0, 0, this.width, this.height);
    ctx.fillStyle = COLORS.background;
    ctx.fillRect(0, 0, this.width, this.height);
    this.drawGrid();
    if (this.showSequence && sequence) {
      this.drawSequence(sequence, placed, next);
    }
    for (const [width, x, z, angle] of blocks) {
      this.drawBlock(width, x, z, angle, COLORS.block, COLORS.blockEdge);
      this.markIfOutside(width, x, z);
    }
    if (ghost) {
      const z = (ghost.layer + 0.5) * this.grid.block_height;
      const [fill, edge] = ghost.legal ? [COLORS.legal, COLORS.legalEdge] : [COLORS.illegal, COLORS.illegalEdge];
      this.drawBlock(ghost.width, ghost.x, z, 0, fill, edge, ghost.legal ? [] : [5, 3]);
    }
  }

  drawGrid() {
    const { ctx, grid, ppu } = this;
    const [left, top] = this.toPixel(-grid.half_width, grid.height);
    const [right, bottom] = this.toPixel(grid.half_width, 0);
    ctx.fillStyle = COLORS.gridFill;
    ctx.fillRect(left, top, right - left, bottom - top);

    const bh = grid.block_height;
    for (let layer = 0; (layer + 1) * bh <= grid.height + 1e-9; layer += 1) {
      if (layer % 2 === 1) {
        const [, y] = this.toPixel(0, (layer + 1) * bh);
        ctx.fillStyle = COLORS.bandFill;
        ctx.fillRect(left, y, right - left, bh * ppu);
      }
    }
    ctx.strokeStyle = COLORS.gridLine;
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let x = -grid.half_width + 1; x < grid.half_width; x += 1) {
      const [px] = this.toPixel(x, 0);
      ctx.moveTo(px, top);
      ctx.lineTo(px, bottom);
    }
    ctx.stroke();

    ctx.strokeStyle = COLORS.gridBorder;
    ctx.strokeRect(left, top, right - left, bottom - top);

    ctx.fillStyle = COLORS.ground;
    ctx.fillRect(0, bottom, this.width, GROUND_DEPTH * ppu);
    ctx.fillStyle = COLORS.background;
    const [cx] = this.toPixel(0, 0);
    ctx.beginPath();
    ctx.moveTo(cx, bottom + 2);
    ctx.lineTo(cx - 6, bottom + 10);
    ctx.lineTo(cx + 6, bottom + 10);
    ctx.closePath();
    ctx.fill();
  }

  /** An arrow at the canvas's edge for a block that lies (partly) beyond it, at the block's height. */
  markIfOutside(width, x, z) {
    const { ctx, ppu } = this;
    const halfView = this.width / 2 / ppu;
    if (Math.abs(x) + width / 2 <= halfView) return;
    const side = Math.sign(x);
    const size = Math.max(8, 0.22 * ppu);
    const [, py] = this.toPixel(0, Math.min(Math.max(z, 0.3), this.grid.height));
    const edgeX = side > 0 ? this.width - 2 : 2;
    ctx.save();
    ctx.fillStyle = COLORS.blockEdge;
    ctx.beginPath();
    ctx.moveTo(edgeX, py);
    ctx.lineTo(edgeX - side * size, py - size * 0.7);
    ctx.lineTo(edgeX - side * size, py + size * 0.7);
    ctx.closePath();
    ctx.fill();
    ctx.restore();
  }

  drawBlock(width, x, z, angle, fill, edge, dash = []) {
    const { ctx, ppu } = this;
    const [px, py] = this.toPixel(x, z);
    const w = width * ppu;
    const h = this.grid.block_height * ppu;
    ctx.save();
    ctx.translate(px, py);
    ctx.rotate(-(angle || 0));
    ctx.fillStyle = fill;
    ctx.fillRect(-w / 2, -h / 2, w, h);
    ctx.strokeStyle = edge;
    ctx.lineWidth = 2;
    ctx.setLineDash(dash);
    ctx.strokeRect(-w / 2 + 1, -h / 2 + 1, w - 2, h - 2);
    ctx.restore();
  }

  drawSequence(sequence, placed, next) {
    const { ctx, ppu } = this;
    const gap = 0.3;
    const total = sequence.reduce((sum, w) => sum + w, 0) + gap * (sequence.length - 1);
    const available = this.width / ppu - 1;
    const scale = Math.min(0.8, available / total);
    const h = this.grid.block_height * scale * ppu;
    const y = TOP_PADDING * ppu * 0.5 + (SEQUENCE_STRIP * ppu - h) / 2 - 4;
    let px = (this.width - total * scale * ppu) / 2;
    sequence.forEach((width, i) => {
      const w = width * scale * ppu;
      let fill = COLORS.block;
      let edge = COLORS.blockEdge;
      if (i === next) {
        [fill, edge] = [COLORS.next, COLORS.nextEdge];
      } else if (i < placed) {
        [fill, edge] = [COLORS.placedInSequence, COLORS.placedEdge];
      }
      ctx.fillStyle = fill;
      ctx.fillRect(px, y, w, h);
      ctx.strokeStyle = edge;
      ctx.lineWidth = i === next ? 3 : 1.5;
      ctx.strokeRect(px, y, w, h);
      if (i === next) {
        ctx.fillStyle = COLORS.nextEdge;
        ctx.font = `bold ${Math.round(0.26 * ppu)}px system-ui, sans-serif`;
        ctx.textAlign = "center";
        ctx.textBaseline = "top";
        ctx.fillText("next", px + w / 2, y + h + 3);
      }
      px += w + gap * scale * ppu;
    });
    const [, gridTop] = this.toPixel(0, this.grid.height);
    ctx.strokeStyle = COLORS.gridLine;
    ctx.beginPath();
    ctx.moveTo(0, gridTop - TOP_PADDING * ppu * 0.5);
    ctx.lineTo(this.width, gridTop - TOP_PADDING * ppu * 0.5);
    ctx.stroke();
  }
}

/**
 * Draws a finished tower, e.g. for a feedback screen: `tower` as `[width, x, layer]` blocks, or
 * `poses` as `[width, x, z, angle]` blocks (a collapsed tower's last frame).
 */
export function renderTower(canvas, { tower = null, poses = null, grid = DEFAULT_GRID, pixelsPerUnit = 30 } = {}) {
  const scene = new TowerScene(canvas, { grid, pixelsPerUnit, showSequence: false });
  const blocks = poses ?? tower.map(([w, x, layer]) => [w, x, (layer + 0.5) * grid.block_height, 0]);
  scene.draw({ blocks });
  return scene;
}
