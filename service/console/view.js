// The 3-D view (three.js): clouds as points, orbitable; and the gallery's thumbnails, drawn by
// one offscreen renderer. A cloud is {points: Float32Array of x y z, color, transform?, size?},
// with transform the answer's 4x4 row-major [[R, t], [0, 0, 0, 1]] (scene = R @ model + t) and
// size its points' size relative to the others'.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const BACKGROUND = 0x0f1114;

function pointsObject({ points, color, transform, size: relative = 1 }, size) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(points, 3));
  const material = new THREE.PointsMaterial({ color, size: size * relative, sizeAttenuation: true });
  const object = new THREE.Points(geometry, material);
  if (transform) placeAt(object, transform);
  return object;
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

  // Draw the clouds, replacing what was drawn; axes (of the model frame) at a transform.
  show(clouds, { viewpoint = null, axesAt = null } = {}) {
    dispose(this.group);
    const sphere = bounds(clouds);
    const size = sphere.radius * 0.012;
    for (const cloud of clouds) this.group.add(pointsObject(cloud, size));
    if (axesAt) {
      const axes = new THREE.AxesHelper(sphere.radius * 0.4);
      placeAt(axes, axesAt);
      this.group.add(axes);
    }
    const { centre } = frame(this.camera, sphere, viewpoint);
    this.controls.target.copy(centre);
    this.controls.update();
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
    const object = pointsObject(cloud, sphere.radius * 0.03);
    this.scene.add(object);
    frame(this.camera, sphere, null);
    this.renderer.render(this.scene, this.camera);
    canvas.getContext("2d").drawImage(this.renderer.domElement, 0, 0, canvas.width, canvas.height);
    this.scene.remove(object);
    object.geometry.dispose();
    object.material.dispose();
  }
}
