// The frames of the 3-D view while the scan's volume shows (viewer.js hands them here).
//
// Two qualities. While the camera moves (or the window changes) a frame is *fast*: the
// surfaces and the volume drawn into targets of a quarter of the canvas's CSS pixels a
// side, with a ray step of two voxels, and stretched over the canvas. Once nothing has
// changed for SETTLE_MS, one *full* frame follows: the surfaces at the canvas's size,
// the volume with a step of one voxel. In software WebGL (SwiftShader, as CI and many
// hospital desktops have it) a full frame of CThead takes about a second; a fast one a
// tenth of that, so turning follows the hand.
//
// Each frame: the surfaces into a target whose depth then ends the volume's rays where a
// surface is (the surfaces hide what lies behind them), its colour copied to the
// canvas; then the volume, blended over it.

import * as THREE from 'three';

// Of the canvas's CSS pixels a side, in a fast frame: at most MAX_SCALE, down to
// MIN_SCALE, as fast frames take longer than FAST_MS from asked for to finished on the
// GPU (the device and its load decide, as VTK's desired update rate does).
export const MAX_SCALE = 0.25;
export const MIN_SCALE = 0.1;
const FAST_MS = 50;
// Voxels a ray step in a fast frame (the opacity is corrected for the step).
export const FAST_STEP = 2;
// Quiet this long (ms) and the full frame is drawn.
const SETTLE_MS = 200;

// A quad that draws a texture over the canvas: a linear surface colour converted to the
// canvas's colour space, or (premultiplied) the volume's colour blended over what is there.
function fullScreenQuad( texture, { blend = false } = {} ) {
	const convert = blend ? '' : '\n#include <colorspace_fragment>\n';
	const material = new THREE.ShaderMaterial( {
		uniforms: { map: { value: texture } },
		vertexShader: 'varying vec2 vUv; void main() { vUv = uv; gl_Position = vec4( position.xy, 0.0, 1.0 ); }',
		fragmentShader: `uniform sampler2D map; varying vec2 vUv; void main() { gl_FragColor = texture2D( map, vUv ); ${convert} }`,
		depthTest: false, depthWrite: false, transparent: blend,
		blending: blend ? THREE.CustomBlending : THREE.NormalBlending,
		blendSrc: THREE.OneFactor, blendDst: THREE.OneMinusSrcAlphaFactor,
		blendSrcAlpha: THREE.OneFactor, blendDstAlpha: THREE.OneMinusSrcAlphaFactor,
	} );
	const scene = new THREE.Scene();
	const quad = new THREE.Mesh( new THREE.PlaneGeometry( 2, 2 ), material );
	quad.frustumCulled = false;
	scene.add( quad );
	return { scene, camera: new THREE.OrthographicCamera( - 1, 1, 1, - 1, 0, 1 ) };
}

// then() once the GPU has finished what has been asked of it so far (a fence, looked at
// every few ms); at once where there are no fences.
export function whenFinished( renderer, then ) {
	const gl = renderer.getContext();
	const sync = gl.fenceSync ? gl.fenceSync( gl.SYNC_GPU_COMMANDS_COMPLETE, 0 ) : null;
	if ( ! sync ) return then();
	gl.flush();
	const look = () => {
		if ( gl.isContextLost() || gl.getSyncParameter( sync, gl.SYNC_STATUS ) === gl.SIGNALED ) {
			if ( ! gl.isContextLost() ) gl.deleteSync( sync );
			then();
		} else setTimeout( look, 4 );
	};
	look();
}

function surfaceTarget() {
	return new THREE.WebGLRenderTarget( 1, 1, { type: THREE.HalfFloatType, depthTexture: new THREE.DepthTexture( 1, 1 ) } );
}

export class VolumePass {
	// requestRender(): asks the viewer for a frame (the full one, once things settle).
	constructor( requestRender ) {
		this.requestRender = requestRender;
		this.full = { surfaces: surfaceTarget() };
		this.fast = { surfaces: surfaceTarget(), volume: new THREE.WebGLRenderTarget( 1, 1 ) };
		for ( const t of [ this.full, this.fast ] ) t.copy = fullScreenQuad( t.surfaces.texture );
		this.fast.blend = fullScreenQuad( this.fast.volume.texture, { blend: true } );
		this.scale = MAX_SCALE;
		this.fastFrames = 0;
		this.step = FAST_STEP;
		this.seen = null; // what the last frame showed: camera, canvas size, volume version
		this.timer = 0;
		this.quality = null; // of the last frame: 'fast' or 'full'
		this.fullStartedAt = 0; // performance.now() when the last full frame was asked for
	}

	// Draws one frame of scene (the surfaces) and volume (a VolumeLayer) with camera;
	// returns its quality.
	render( renderer, scene, camera, volume, background ) {
		const key = [ ...camera.projectionMatrix.elements, ...camera.matrixWorld.elements,
			...renderer.getDrawingBufferSize( new THREE.Vector2() ).toArray(), volume.version ].join();
		const moved = key !== this.seen;
		this.seen = key;
		clearTimeout( this.timer );
		if ( moved ) {
			this.timer = setTimeout( () => this.requestRender(), SETTLE_MS );
			const start = performance.now();
			this.drawFast( renderer, scene, camera, volume, background );
			// The first frame also uploads the voxels and compiles the shader: not a measure.
			if ( this.fastFrames ++ > 0 ) whenFinished( renderer, () => this.adapt( performance.now() - start ) );
		} else {
			this.fullStartedAt = performance.now();
			this.drawFull( renderer, scene, camera, volume, background );
		}
		this.quality = moved ? 'fast' : 'full';
		return this.quality;
	}

	// The next fast frame's scale after one took ms: a step towards FAST_MS, in 1/40ths.
	adapt( ms ) {
		const step = Math.min( 1.25, Math.max( 0.8, Math.sqrt( FAST_MS / Math.max( ms, 1 ) ) ) );
		const scale = Math.round( this.scale * step * 40 ) / 40;
		this.scale = Math.min( MAX_SCALE, Math.max( MIN_SCALE, scale ) );
	}

	drawFull( r, scene, camera, volume, background ) {
		const size = r.getDrawingBufferSize( new THREE.Vector2() );
		this.drawSurfaces( r, scene, camera, background, this.full, size );
		volume.setDepth( this.full.surfaces.depthTexture, camera );
		volume.setStep( 1 );
		r.render( volume.mesh, camera );
	}

	drawFast( r, scene, camera, volume, background ) {
		const css = r.getSize( new THREE.Vector2() );
		const buffer = r.getDrawingBufferSize( new THREE.Vector2() );
		const size = css.multiplyScalar( this.scale ).round().max( new THREE.Vector2( 1, 1 ) ).min( buffer );
		this.drawSurfaces( r, scene, camera, background, this.fast, size );
		this.fast.volume.setSize( size.x, size.y );
		r.setRenderTarget( this.fast.volume );
		r.setClearColor( 0x000000, 0 );
		r.clear();
		volume.setDepth( this.fast.surfaces.depthTexture, camera );
		volume.setStep( this.step );
		r.render( volume.mesh, camera );
		r.setRenderTarget( null );
		r.setClearColor( background );
		r.render( this.fast.blend.scene, this.fast.blend.camera );
	}

	// The surfaces into the target of a size, then copied to the canvas.
	drawSurfaces( r, scene, camera, background, targets, size ) {
		targets.surfaces.setSize( size.x, size.y );
		r.setRenderTarget( targets.surfaces );
		r.setClearColor( background );
		r.clear();
		r.render( scene, camera );
		r.setRenderTarget( null );
		r.render( targets.copy.scene, targets.copy.camera );
	}

	dispose() {
		clearTimeout( this.timer );
		for ( const t of [ this.full.surfaces, this.fast.surfaces, this.fast.volume ] ) t.dispose();
	}
}
