/* The trajectory canvas's geometry: pure functions, no DOM, no state.
 *
 * Three coordinate systems meet on the canvas: the table in mm (the planned
 * path's poses), the camera image in px (the frame under the path, mapped to
 * the table by the robot calibration's image → table homography), and the
 * canvas in CSS px. Kept apart from the drawing so that node can test them
 * (tests/unit/hmi/, run from tests/unit/test_hmi_geometry.py).
 */

/** Margin (CSS px) around a path drawn by its own bounds, with no image under it. */
export const PATH_MARGIN = 40;

/** The smallest window of the image shown around a path (image px, its width). */
export const MIN_WINDOW = 240;

/** How much of the image around the path the window shows, per side of its box. */
export const WINDOW_ZOOM = 2.4;

/** The inverse of a 3×3 matrix (rows), or null when it is singular. */
export function invert3(m) {
  const [[a, b, c], [d, e, f], [g, h, i]] = m;
  const A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
  const det = a * A + b * B + c * C;
  if (!det) return null;
  return [
    [A / det, -(b * i - c * h) / det, (b * f - c * e) / det],
    [B / det, (a * i - c * g) / det, -(a * f - c * d) / det],
    [C / det, -(a * h - b * g) / det, (a * e - b * d) / det],
  ];
}

/** Table mm → image px: the inverse of the calibration's image → robot homography.
 * Null without a homography, or with a singular one. */
export function tableToImage(homography) {
  const inverse = homography && invert3(homography);
  if (!inverse) return null;
  return ([x, y]) => {
    const w = inverse[2][0] * x + inverse[2][1] * y + inverse[2][2];
    return [
      (inverse[0][0] * x + inverse[0][1] * y + inverse[0][2]) / w,
      (inverse[1][0] * x + inverse[1][1] * y + inverse[1][2]) / w,
    ];
  };
}

/** The axis-aligned bounds {x, y, w, h} of [x, y, ...] points (at least one). */
export function boundingBox(points) {
  const xs = points.map((p) => p[0]);
  const ys = points.map((p) => p[1]);
  const x = Math.min(...xs), y = Math.min(...ys);
  return { x, y, w: Math.max(...xs) - x, h: Math.max(...ys) - y };
}

/** A window of the image around the path, in the canvas's aspect ratio, inside the image. */
export function viewWindow(box, aspect, imageW, imageH) {
  let w = Math.max(box.w * WINDOW_ZOOM, box.h * WINDOW_ZOOM * aspect, MIN_WINDOW);
  let h = w / aspect;
  if (w > imageW) [w, h] = [imageW, imageW / aspect];
  if (h > imageH) [w, h] = [imageH * aspect, imageH];
  const cx = box.x + box.w / 2, cy = box.y + box.h / 2;
  const x = Math.min(Math.max(cx - w / 2, 0), imageW - w);
  const y = Math.min(Math.max(cy - h / 2, 0), imageH - h);
  return { x, y, w, h };
}

/** Image px → canvas px, for the window `box` of the image stretched over the canvas. */
export function windowToCanvas(box, width, height) {
  return ([u, v]) => [((u - box.x) * width) / box.w, ((v - box.y) * height) / box.h];
}

/** Table mm → canvas px with no image: the path's bounds `box` fitted and centred,
 * one scale for both axes, y up as on the table (the canvas's y points down). */
export function fitToCanvas(box, width, height, margin = PATH_MARGIN) {
  const scale = Math.min((width - 2 * margin) / (box.w || 1), (height - 2 * margin) / (box.h || 1));
  const ox = (width - box.w * scale) / 2, oy = (height - box.h * scale) / 2;
  return ([x, y]) => [ox + (x - box.x) * scale, height - (oy + (y - box.y) * scale)];
}

/** Where a whole image goes on the canvas: letterboxed, undistorted in shape. */
export function containRect(imageW, imageH, width, height) {
  const scale = Math.min(width / imageW, height / imageH);
  const w = imageW * scale, h = imageH * scale;
  return { x: (width - w) / 2, y: (height - h) / 2, w, h };
}

/** The canvas's size in CSS px (whole, at least 1) for its box, and its backing store's
 * in device px: sharp lines on a high-density screen. */
export function canvasSize(box, ratio) {
  const width = Math.max(1, Math.round(box.width));
  const height = Math.max(1, Math.round(box.height));
  return { width, height, pixelWidth: width * ratio, pixelHeight: height * ratio };
}
