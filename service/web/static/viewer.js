// Interactive 3D view of a job: the result mesh (GLB) with an optional wireframe, and the input points (PLY).
// Loaded lazily by app.js, so the form keeps working even if three.js is not installed.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';

const BACKGROUND = 0xf4f5f8;
const FACE_COLOR = 0xb8c7e0;
const WIRE_COLOR = 0x1a1f29;
const POINT_COLOR = 0xe36b29;

// True when WebGL runs on a CPU rasteriser.  Asked of a throw-away context, before the real one is made.
function isSoftwareGL() {
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    if (!gl) return true;
    const info = gl.getExtension('WEBGL_debug_renderer_info');
    const name = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
    gl.getExtension('WEBGL_lose_context')?.loseContext();
    return /swiftshader|llvmpipe|softpipe|software/i.test(String(name));
  } catch {
    return false;
  }
}

export class Viewer {
  constructor(container) {
    this.container = container;
    // preserveDrawingBuffer: the canvas can be read back (screenshots, tests) after a frame is shown.
    // On a software rasteriser (no GPU: SwiftShader, llvmpipe) multisampling and high-DPI buffers cost
    // seconds per frame on a dense mesh, so they are dropped there.
    this.software = isSoftwareGL();
    this.renderer = new THREE.WebGLRenderer({ antialias: !this.software, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(this.software ? 1 : Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setClearColor(BACKGROUND, 1);
    container.appendChild(this.renderer.domElement);

    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
    this.scene.add(this.camera);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x8890a0, 1.6));
    const key = new THREE.DirectionalLight(0xffffff, 1.8);
    key.position.set(-0.4, 0.6, 1.0); // follows the camera: every view is lit from the viewer's upper left
    this.camera.add(key);

    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    // Render on demand, not in a loop; a drag fires many 'change' events per frame: draw once per frame.
    this.controls.addEventListener('change', () => this.renderSoon());
    this.frameRequested = false;

    this.mesh = null;    // THREE.Group of the result
    this.wire = null;    // THREE.Group of LineSegments over the result
    this.points = null;  // THREE.Points of the input
    this.wireOn = true;
    this.pointsOn = true;

    this.resizer = new ResizeObserver(() => this.resize());
    this.resizer.observe(container);
    this.resize();
  }

  resize() {
    const w = Math.max(1, this.container.clientWidth), h = Math.max(1, this.container.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() { this.renderer.render(this.scene, this.camera); }

  renderSoon() {
    if (this.frameRequested) return;
    this.frameRequested = true;
    requestAnimationFrame(() => { this.frameRequested = false; this.render(); });
  }

  clear() {
    for (const obj of [this.mesh, this.wire, this.points]) {
      if (!obj) continue;
      this.scene.remove(obj);
      obj.traverse((o) => { o.geometry?.dispose(); o.material?.dispose(); });
    }
    this.mesh = this.wire = this.points = null;
    this.render();
  }

  // GLB bytes -> shaded faces + wireframe.  Returns {vertices, faces} as drawn.
  async showMesh(buffer) {
    const gltf = await new GLTFLoader().parseAsync(buffer, '');
    for (const obj of [this.mesh, this.wire]) if (obj) this.scene.remove(obj);
    const group = new THREE.Group(), wire = new THREE.Group();
    let vertices = 0, faces = 0;
    gltf.scene.updateMatrixWorld(true);
    gltf.scene.traverse((o) => {
      if (!o.isMesh) return;
      const geom = o.geometry.clone().applyMatrix4(o.matrixWorld);
      vertices += geom.attributes.position.count;
      faces += (geom.index ? geom.index.count : geom.attributes.position.count) / 3;
      // Artist meshes are meant to be seen flat; their winding may be inconsistent, so both sides are lit.
      // polygonOffset pushes faces back a little so the wire over them does not z-fight.
      const mat = new THREE.MeshStandardMaterial({
        color: FACE_COLOR, flatShading: true, side: THREE.DoubleSide, roughness: 0.85, metalness: 0,
        polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1,
      });
      group.add(new THREE.Mesh(geom, mat));
      const lines = new THREE.LineSegments(new THREE.WireframeGeometry(geom),
        new THREE.LineBasicMaterial({ color: WIRE_COLOR, transparent: true, opacity: 0.55 }));
      wire.add(lines);
    });
    this.mesh = group;
    this.wire = wire;
    wire.visible = this.wireOn;
    this.scene.add(group, wire);
    this.frame();
    return { vertices, faces: Math.round(faces) };
  }

  // PLY point bytes -> small round-ish points; the view is framed on them if no mesh is shown yet.
  showPoints(buffer) {
    const geom = new PLYLoader().parse(buffer);
    if (this.points) this.scene.remove(this.points);
    const n = geom.attributes.position.count;
    // Dots of a fixed size on screen (pixels): sparse clouds get bigger ones, dense ones must not hide the mesh.
    const size = Math.min(4, Math.max(1.5, 160 / Math.sqrt(Math.max(n, 1)))) * this.renderer.getPixelRatio();
    this.points = new THREE.Points(geom, new THREE.PointsMaterial({ color: POINT_COLOR, size, sizeAttenuation: false }));
    this.points.visible = this.pointsOn;
    this.scene.add(this.points);
    if (!this.mesh) this.frame();
    else this.render();
    return n;
  }

  setWireframe(on) { this.wireOn = on; if (this.wire) this.wire.visible = on; this.render(); }
  setPoints(on) { this.pointsOn = on; if (this.points) this.points.visible = on; this.render(); }

  // Look at everything shown from a fixed 3/4 view (the same direction as the PNG previews).
  frame() {
    const box = new THREE.Box3();
    for (const obj of [this.mesh, this.points]) if (obj) box.expandByObject(obj);
    if (box.isEmpty()) { this.render(); return; }
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    const radius = Math.max(sphere.radius, 1e-6);
    const az = THREE.MathUtils.degToRad(35), el = THREE.MathUtils.degToRad(25);
    const dir = new THREE.Vector3(Math.cos(el) * Math.sin(az), Math.sin(el), Math.cos(el) * Math.cos(az));
    const fit = Math.min(this.camera.fov, this.camera.fov * this.camera.aspect);
    const dist = radius / Math.sin(THREE.MathUtils.degToRad(fit) / 2) * 1.05;
    this.camera.position.copy(sphere.center).addScaledVector(dir, dist);
    this.camera.near = dist / 100;
    this.camera.far = dist * 100;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(sphere.center);
    this.controls.update();
    this.render();
  }
}
