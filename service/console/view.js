// The 3-D view (three.js): clouds as points, orbitable; and the gallery's thumbnails, drawn by
// one offscreen renderer. A cloud is {points: Float32Array of x y z, color, transform?, size?,
// pointSize?, ahead?, colors?, tag?, name?}, with transform the answer's 4x4 row-major
// [[R, t], [0, 0, 0, 1]] (scene = R @ model + t), size its points' size relative to the
// others' (pointSize: in the cloud's units instead), ahead how far (in the cloud's units)
// towards the eye its points are drawn (so that they win over others' on the same surface),
// colors r g b for each point in place of color (components from rgb()), tag what highlight()
// picks it by, name what repaint() finds it by.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const BACKGROUND = 0x0f1114;

// A colour's components as vertex colours take them (three.js's linear working space).
export function rgb(hex) {
  const { r, g, b } = new THREE.Color(hex);
  return [r, g, b];
}

// base: the points' size, as PointsMaterial takes it (the view's height at distance 1 is 2)
function pointsObject({ points, color, colors, transform, tag, name, pointSize, ahead, size: relative = 1 }, base, fov) {
  const size = pointSize ? pointSize / Math.tan(THREE.MathUtils.degToRad(fov / 2)) : base * relative;
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(points, 3));
  if (colors) geometry.setAttribute("color", new THREE.BufferAttribute(colors, 3));
  const material = new THREE.PointsMaterial({
    color: colors ? 0xffffff : color,
    vertexColors: Boolean(colors),
    size,
    sizeAttenuation: true,
  });
  if (ahead) drawAhead(material, ahead);
  const object = new THREE.Points(geometry, material);
  object.userData = { tag, size };
  if (name) object.name = name;
  if (transform) placeAt(object, transform);
  return object;
}

// The material's points moved ahead (world units) along the eye's rays: where they are.
function drawAhead(material, ahead) {
  material.onBeforeCompile = (shader) => {
    shader.uniforms.ahead = { value: ahead };
    shader.vertexShader = `uniform float ahead;\n${shader.vertexShader}`.replace(
      "#include <project_vertex>",
      `#include <project_vertex>
      mvPosition.xyz *= max(0.0, 1.0 - ahead / length(mvPosition.xyz));
      gl_Position = projectionMatrix * mvPosition;`,
    );
  };
  material.customProgramCacheKey = () => "ahead";
}

function placeAt(object, transform) {
  object.matrixAutoUpdate = false;
  object.matrix.set(...transform.flat()); // Matrix4.set takes row-major values
  object.updateMatrixWorld(true);
}

function bounds(clouds) {
  const box = new THREE.Box3();
  const point = new THREE.Vector3();
  for (const { points, transform } of clouds) {
    const matrix = new THREE.Matrix4();
    if (transform) matrix.set(...transform.flat());
    for (let i = 0; i < points.length; i += 3) {
      box.expandByPoint(point.set(points[i], points[i + 1], points[i + 2]).applyMatrix4(matrix));
    }
  }
  return box.getBoundingSphere(new THREE.Sphere());
}

function dispose(group) {
  for (const child of [...group.children]) {
    group.remove(child);
    child.geometry?.dispose();
    child.material?.dispose();
  }
}

// Look at the sphere from the viewpoint's side when there is one (y down, as a camera's frame
// has it), else from an oblique corner with z up.
function frame(camera, sphere, viewpoint) {
  const centre = sphere.center;
  const radius = Math.max(sphere.radius, 1e-6);
  let direction = new THREE.Vector3(1, -1.4, 0.9);
  camera.up.set(0, 0, 1);
  if (viewpoint) {
    const towards = new THREE.Vector3(...viewpoint).sub(centre);
    if (towards.lengthSq() > 0) {
      direction = towards;
      camera.up.set(0, -1, 0);
    }
  }
  const distance = radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.15;
  camera.position.copy(centre).addScaledVector(direction.normalize(), distance);
  camera.near = distance / 100;
  camera.far = distance * 100;
  camera.lookAt(centre);
  camera.updateProjectionMatrix();
  return { centre, radius };
}

export class View {
  constructor(element) {
    this.element = element;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    element.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.group = new THREE.Group();
    this.scene.add(this.group);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    new ResizeObserver(() => this.resize()).observe(element);
    this.resize();
  }

  // Draw the clouds, replacing what was drawn, looking at all of them or at those in fit (the
  // rest may lie outside the view); axes (of the model frame) at a transform.
  show(clouds, { viewpoint = null, axesAt = null, fit = null } = {}) {
    dispose(this.group);
    const sphere = bounds(fit?.length ? fit : clouds);
    this.axesLength = sphere.radius * 0.4;
    const size = sphere.radius * 0.012;
    for (const cloud of clouds) this.group.add(pointsObject(cloud, size, this.camera.fov));
    this.placeAxes(axesAt);
    const { centre } = frame(this.camera, sphere, viewpoint);
    this.controls.target.copy(centre);
    this.controls.update();
    this.render();
  }

  placeAxes(transform, length = this.axesLength) {
    for (const child of this.group.children.filter((c) => c.userData.axes)) {
      this.group.remove(child);
      child.dispose();
    }
    if (!transform) return;
    const axes = new THREE.AxesHelper(length);
    axes.userData = { axes: true };
    placeAt(axes, transform);
    this.group.add(axes);
  }

  // New colours (as many as before) for the cloud named name.
  repaint(name, colors) {
    const attribute = this.group.getObjectByName(name)?.geometry.getAttribute("color");
    if (!attribute) return;
    attribute.array.set(colors);
    attribute.needsUpdate = true;
    this.render();
  }

  // The cloud tagged tag drawn larger, with its model frame's axes at its transform, and the
  // other tagged ones faint (tag null: all as drawn, no axes).
  highlight(tag) {
    let picked = null;
    for (const child of this.group.children) {
      const { tag: own, size } = child.userData;
      if (own === undefined) continue;
      const faint = tag !== null && own !== tag;
      if (own === tag) picked = child;
      child.material.size = own === tag ? size * 1.3 : size;
      child.material.transparent = faint;
      child.material.opacity = faint ? 0.25 : 1;
      child.material.needsUpdate = true;
    }
    if (picked) {
      picked.geometry.computeBoundingSphere();
      const transform = picked.matrix.toArray(); // column-major
      const rows = [0, 1, 2, 3].map((r) => [0, 1, 2, 3].map((c) => transform[4 * c + r]));
      this.placeAxes(rows, picked.geometry.boundingSphere.radius * 1.3);
    } else {
      this.placeAxes(null);
    }
    this.render();
  }

  resize() {
    const { clientWidth: width, clientHeight: height } = this.element;
    if (!width || !height) return;
    this.renderer.setSize(width, height);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
  }
}

export class Thumbnails {
  constructor(width = 160, height = 120) {
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setSize(width, height);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(40, width / height, 0.01, 100);
  }

  // Render one cloud and copy the picture onto a 2-D canvas.
  draw(cloud, canvas) {
    const sphere = bounds([cloud]);
    const object = pointsObject(cloud, sphere.radius * 0.03, this.camera.fov);
    this.scene.add(object);
    frame(this.camera, sphere, null);
    this.renderer.render(this.scene, this.camera);
    canvas.getContext("2d").drawImage(this.renderer.domElement, 0, 0, canvas.width, canvas.height);
    this.scene.remove(object);
    object.geometry.dispose();
    object.material.dispose();
  }
}
