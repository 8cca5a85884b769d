// The dashboard's canvas geometry (clients/hmi/geometry.js), with node's own test
// runner: `node --test tests/unit/hmi/`, run by tests/unit/test_hmi_geometry.py.

import assert from "node:assert/strict";
import { describe, test } from "node:test";

import {
  MIN_WINDOW,
  PATH_MARGIN,
  boundingBox,
  canvasSize,
  containRect,
  fitToCanvas,
  invert3,
  tableToImage,
  viewWindow,
  windowToCanvas,
} from "../../../clients/hmi/geometry.js";

const EPSILON = 1e-9;

function close(actual, expected, message) {
  assert.equal(actual.length, expected.length, message);
  actual.forEach((value, i) => {
    if (Array.isArray(value)) return close(value, expected[i], message);
    assert.ok(Math.abs(value - expected[i]) < EPSILON, `${message}: ${actual} ≠ ${expected}`);
  });
}

function multiply(a, b) {
  return a.map((row) => b[0].map((_, j) => row.reduce((sum, v, k) => sum + v * b[k][j], 0)));
}

/** Image px → table mm, as the robot calibration fits it: a projective map. */
function applyHomography(h, [u, v]) {
  const w = h[2][0] * u + h[2][1] * v + h[2][2];
  return [(h[0][0] * u + h[0][1] * v + h[0][2]) / w, (h[1][0] * u + h[1][1] * v + h[1][2]) / w];
}

const IDENTITY = [
  [1, 0, 0],
  [0, 1, 0],
  [0, 0, 1],
];
// 0.5 mm per px, the image's y pointing the other way, the origin moved, a little perspective.
const IMAGE_TO_TABLE = [
  [0.5, 0.02, -120],
  [0.01, -0.5, 300],
  [1e-5, 2e-5, 1],
];

describe("invert3", () => {
  test("inverts the identity to itself", () => {
    close(invert3(IDENTITY), IDENTITY, "identity");
  });

  test("gives the inverse of a projective matrix", () => {
    close(multiply(IMAGE_TO_TABLE, invert3(IMAGE_TO_TABLE)), IDENTITY, "H·H⁻¹");
    close(multiply(invert3(IMAGE_TO_TABLE), IMAGE_TO_TABLE), IDENTITY, "H⁻¹·H");
  });

  test("is null for a singular matrix", () => {
    assert.equal(
      invert3([
        [1, 2, 3],
        [2, 4, 6],
        [0, 0, 1],
      ]),
      null,
    );
  });
});

describe("tableToImage", () => {
  test("undoes the calibration's image → table map", () => {
    const toImage = tableToImage(IMAGE_TO_TABLE);
    for (const pixel of [
      [0, 0],
      [640, 480],
      [1919, 1079],
      [321.5, 17.25],
    ]) {
      close(toImage(applyHomography(IMAGE_TO_TABLE, pixel)), pixel, `pixel ${pixel}`);
    }
  });

  test("is null without a calibration or with a singular one", () => {
    assert.equal(tableToImage(undefined), null);
    assert.equal(tableToImage(null), null);
    assert.equal(
      tableToImage([
        [0, 0, 0],
        [0, 1, 0],
        [0, 0, 1],
      ]),
      null,
    );
  });
});

describe("boundingBox", () => {
  test("spans the points", () => {
    const points = [
      [10, -5, 99],
      [-3, 20, 0],
      [7, 7, 5],
    ];
    assert.deepEqual(boundingBox(points), { x: -3, y: -5, w: 13, h: 25 });
  });

  test("of one point is empty, at the point", () => {
    assert.deepEqual(boundingBox([[4, 2]]), { x: 4, y: 2, w: 0, h: 0 });
  });
});

describe("viewWindow", () => {
  const inside = (window, imageW, imageH) => {
    assert.ok(window.x >= 0 && window.y >= 0, `origin ${window.x},${window.y}`);
    assert.ok(window.x + window.w <= imageW + EPSILON, "right edge inside the image");
    assert.ok(window.y + window.h <= imageH + EPSILON, "bottom edge inside the image");
  };

  test("is centred on the path, zoomed out around it, in the canvas's aspect", () => {
    const box = { x: 900, y: 500, w: 200, h: 100 };
    const window = viewWindow(box, 16 / 9, 1920, 1080);
    assert.ok(Math.abs(window.w / window.h - 16 / 9) < EPSILON);
    assert.equal(window.w, 480); // 2.4 × the path's width
    close([window.x + window.w / 2, window.y + window.h / 2], [1000, 550], "centre");
    inside(window, 1920, 1080);
  });

  test("keeps a minimum size around a tiny path", () => {
    const window = viewWindow({ x: 100, y: 100, w: 1, h: 1 }, 2, 1920, 1080);
    assert.deepEqual([window.w, window.h], [MIN_WINDOW, MIN_WINDOW / 2]);
  });

  test("is moved back inside the image near its edges", () => {
    const window = viewWindow({ x: 1900, y: 1070, w: 10, h: 5 }, 4 / 3, 1920, 1080);
    inside(window, 1920, 1080);
    assert.equal(window.x + window.w, 1920);
    assert.equal(window.y + window.h, 1080);
  });

  test("is at most the whole image, whichever side limits it", () => {
    const wide = viewWindow({ x: 0, y: 0, w: 1800, h: 100 }, 2, 1920, 1080);
    assert.deepEqual(wide, { x: 0, y: 0, w: 1920, h: 960 });
    const tall = viewWindow({ x: 0, y: 0, w: 100, h: 1000 }, 1, 1920, 1080);
    assert.equal(tall.w, 1080);
    assert.equal(tall.h, 1080);
    inside(tall, 1920, 1080);
  });
});

describe("windowToCanvas", () => {
  test("stretches the window over the canvas", () => {
    const toCanvas = windowToCanvas({ x: 100, y: 50, w: 400, h: 200 }, 800, 400);
    close(toCanvas([100, 50]), [0, 0], "top left");
    close(toCanvas([500, 250]), [800, 400], "bottom right");
    close(toCanvas([300, 150]), [400, 200], "centre");
  });
});

describe("fitToCanvas", () => {
  const box = { x: -50, y: 10, w: 200, h: 100 };

  test("fits the path's box inside the margins, centred, y up", () => {
    const toCanvas = fitToCanvas(box, 800, 600);
    // 200 × 100 mm into 720 × 520 px: 3.6 px/mm, limited by the width.
    close(toCanvas([-50, 10]), [PATH_MARGIN, 300 + 180], "lower left of the table: low on the canvas");
    close(toCanvas([150, 110]), [800 - PATH_MARGIN, 300 - 180], "upper right");
    close(toCanvas([50, 60]), [400, 300], "centre");
  });

  test("keeps the path's shape: one scale for both axes", () => {
    const toCanvas = fitToCanvas(box, 500, 1000);
    const [x0, y0] = toCanvas([-50, 10]);
    const [x1, y1] = toCanvas([150, 110]);
    assert.ok(Math.abs((x1 - x0) / (y0 - y1) - 2) < EPSILON);
  });

  test("draws a single point or a straight line without dividing by zero", () => {
    const point = fitToCanvas({ x: 5, y: 5, w: 0, h: 0 }, 400, 300)([5, 5]);
    close(point, [200, 150], "a point in the middle");
    const line = fitToCanvas({ x: 0, y: 0, w: 100, h: 0 }, 400, 300);
    close(line([0, 0]), [PATH_MARGIN, 150], "start");
    close(line([100, 0]), [400 - PATH_MARGIN, 150], "end");
  });
});

describe("containRect", () => {
  test("letterboxes a wide image in a tall canvas", () => {
    assert.deepEqual(containRect(1920, 1080, 960, 1080), { x: 0, y: 270, w: 960, h: 540 });
  });

  test("pillarboxes a tall image in a wide canvas", () => {
    assert.deepEqual(containRect(1000, 2000, 800, 400), { x: 300, y: 0, w: 200, h: 400 });
  });
});

describe("canvasSize", () => {
  test("whole CSS px, at least one, and a backing store in device px", () => {
    assert.deepEqual(canvasSize({ width: 640.4, height: 359.6 }, 2), {
      width: 640,
      height: 360,
      pixelWidth: 1280,
      pixelHeight: 720,
    });
    assert.deepEqual(canvasSize({ width: 0, height: 0.2 }, 1), {
      width: 1,
      height: 1,
      pixelWidth: 1,
      pixelHeight: 1,
    });
  });
});
