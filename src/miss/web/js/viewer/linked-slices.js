// The "Slices" toggle beside "Volume": axial, coronal and sagittal views of the scan beside
// the 3-D view, drawn from the voxels the volume panel fetches (its window, or its first
// preset's), in radiological orientation with edge labels from the scan's affine, each
// visible surface's outline on the slice in its colour, and one crosshair (a patient LPS
// mm point) for all four views: a click on a slice moves the other two, a click on a
// surface in 3-D moves all three (and a marker there), the wheel and the arrow keys step
// through a focused view's slices. ?view=slices in the address opens them, ?at=x,y,z (LPS
// mm) puts the crosshair there; the address follows the crosshair.

import * as THREE from 'three';
import { onClick } from '../format.js';
import { status } from '../test-hooks.js';
import { addressNumbers, setAddressParam, setAddressView } from './deep-link.js';
import { clipSegments, frameOf, imageToVoxel, layoutOf, outline, slicePixels, toLps, toVoxel, voxelToImage } from './slice-geometry.js';

const $ = ( id ) => document.getElementById( id );
const NAMES = [ 'axial', 'coronal', 'sagittal' ];
const PAD = 16; // CSS px about the picture, where the edge labels go
const CROSSHAIR = 'rgba(255, 212, 0, 0.75)';

// One of the three views: a canvas (focusable, a slider of its slice number) with its
// edge labels and its "axial 57 / 113".
class SliceView {
	constructor( panel, name ) {
		this.panel = panel;
		this.name = name;
		this.index = 0;
		this.image = { key: '', canvas: document.createElement( 'canvas' ) };
		this.canvas = Object.assign( document.createElement( 'canvas' ), { tabIndex: 0 } );
		this.canvas.setAttribute( 'role', 'slider' );
		this.canvas.setAttribute( 'aria-label', `${name[ 0 ].toUpperCase()}${name.slice( 1 )} slice` );
		this.labels = Object.fromEntries( [ 'top', 'bottom', 'left', 'right' ].map( ( edge ) => [ edge, Object.assign( document.createElement( 'span' ), { className: `edge ${edge}` } ) ] ) );
		this.readout = Object.assign( document.createElement( 'span' ), { className: 'readout' } );
		this.root = Object.assign( document.createElement( 'div' ), { className: 'slice-view' } );
		this.root.dataset.view = name;
		const pane = Object.assign( document.createElement( 'div' ), { className: 'pane' } );
		pane.append( this.canvas, ...Object.values( this.labels ) );
		this.root.append( pane, this.readout );
		this.bind();
	}

	setLayout( layout ) {
		this.layout = layout;
		for ( const [ edge, span ] of Object.entries( this.labels ) ) span.textContent = layout.labels[ edge ];
		this.canvas.setAttribute( 'aria-valuemin', '1' );
		this.canvas.setAttribute( 'aria-valuemax', String( layout.count ) );
	}

	bind() {
		const c = this.canvas;
		// Nothing to do until the first drawing (the scan may still be on its way).
		const put = ( e ) => this.rect && this.panel.setPoint( this.toLps( e.clientX, e.clientY ) );
		c.addEventListener( 'pointerdown', ( e ) => {
			if ( e.button !== 0 ) return;
			c.focus();
			put( e );
			if ( e.pointerType === 'mouse' ) c.setPointerCapture( e.pointerId ); // drag the crosshair
		} );
		c.addEventListener( 'pointermove', ( e ) => e.pointerType === 'mouse' && c.hasPointerCapture( e.pointerId ) && put( e ) );
		c.addEventListener( 'wheel', ( e ) => {
			e.preventDefault(); // the page stays put: the wheel turns the slices
			if ( e.deltaY && this.rect ) this.panel.step( this, Math.sign( e.deltaY ) );
		}, { passive: false } );
		const keys = { ArrowUp: 1, ArrowRight: 1, ArrowDown: - 1, ArrowLeft: - 1, PageUp: 10, PageDown: - 10 };
		c.addEventListener( 'keydown', ( e ) => {
			if ( ! this.rect ) return;
			const last = this.layout.count - 1;
			const to = e.key === 'Home' ? 0 : e.key === 'End' ? last : e.key in keys ? this.index + keys[ e.key ] : null;
			if ( to == null ) return;
			e.preventDefault();
			this.panel.step( this, to - this.index );
		} );
	}

	// The picture's place on the canvas (CSS px): the slice at its physical aspect, fitted.
	fit( width, height ) {
		const { nU, nV, stepU, stepV } = this.layout;
		const zoom = Math.max( 1e-6, Math.min( ( width - 2 * PAD ) / ( nU * stepU ), ( height - 2 * PAD ) / ( nV * stepV ) ) );
		const w = nU * stepU * zoom;
		const h = nV * stepV * zoom;
		return { x: ( width - w ) / 2, y: ( height - h ) / 2, w, h };
	}

	// Voxel coordinates -> canvas CSS px, and a pointer's place -> patient LPS mm.
	toCanvas( c ) {
		const [ a, b ] = voxelToImage( this.layout, c );
		const r = this.rect;
		return [ r.x + ( a + 0.5 ) * r.w / this.layout.nU, r.y + ( b + 0.5 ) * r.h / this.layout.nV ];
	}

	toLps( clientX, clientY ) {
		const box = this.canvas.getBoundingClientRect();
		const r = this.rect;
		const a = ( clientX - box.left - r.x ) / r.w * this.layout.nU - 0.5;
		const b = ( clientY - box.top - r.y ) / r.h * this.layout.nV - 0.5;
		const clamp = ( x, n ) => Math.min( n - 1, Math.max( 0, x ) );
		return toLps( this.panel.frame, imageToVoxel( this.layout, clamp( a, this.layout.nU ), clamp( b, this.layout.nV ), this.index ) );
	}

	// The slice's pixels under the window, made again only when the slice or window changes.
	picture( level, width ) {
		const key = `${this.index}|${level}|${width}`;
		const { header, data } = this.panel.volume;
		if ( this.image.key !== key ) {
			const { nU, nV } = this.layout;
			Object.assign( this.image.canvas, { width: nU, height: nV } );
			const pixels = slicePixels( header, data, this.layout, this.index, level, width );
			this.image.canvas.getContext( '2d' ).putImageData( new ImageData( pixels, nU, nV ), 0, 0 );
			this.image.key = key;
		}
		return this.image.canvas;
	}

	draw( point, [ level, width ], parts ) {
		const box = this.canvas.getBoundingClientRect();
		const dpr = window.devicePixelRatio || 1;
		Object.assign( this.canvas, { width: Math.max( 1, Math.round( box.width * dpr ) ), height: Math.max( 1, Math.round( box.height * dpr ) ) } );
		const ctx = this.canvas.getContext( '2d' );
		ctx.setTransform( dpr, 0, 0, dpr, 0, 0 );
		ctx.fillStyle = '#000';
		ctx.fillRect( 0, 0, box.width, box.height );
		this.rect = this.fit( box.width, box.height );
		const r = this.rect;
		ctx.imageSmoothingEnabled = true;
		ctx.drawImage( this.picture( level, width ), r.x, r.y, r.w, r.h );
		const drawn = parts.map( ( p ) => this.drawOutline( ctx, p ) );
		this.drawCrosshair( ctx, this.toCanvas( toVoxel( this.panel.frame, point ) ) );
		const text = `${this.name} ${this.index + 1} / ${this.layout.count}`;
		this.readout.textContent = text;
		this.canvas.setAttribute( 'aria-valuenow', String( this.index + 1 ) );
		this.canvas.setAttribute( 'aria-valuetext', text );
		const round = ( x ) => Math.round( x * 100 ) / 100;
		return {
			index: this.index, count: this.layout.count, readout: text, labels: { ...this.layout.labels },
			rect: [ r.x, r.y, r.w, r.h ].map( round ), size: [ box.width, box.height ],
			outlines: drawn.map( ( d ) => ( { part: d.part, colour: d.colour, segments: d.segments.map( ( s ) => s.map( round ) ) } ) ),
		};
	}

	// A part's outline on this slice in its colour: segments [x0, y0, x1, y1] (CSS px).
	drawOutline( ctx, part ) {
		const { voxels, index } = this.panel.voxelsOf( part );
		let cut = outline( voxels, index, this.layout.s, this.index );
		const keep = this.panel.clipInVoxels();
		if ( keep ) cut = clipSegments( cut, keep ); // what the clipping plane cuts away in 3-D
		const segments = cut.map( ( [ p, q ] ) => [ ...this.toCanvas( p ), ...this.toCanvas( q ) ] );
		const colour = `#${part.material.color.getHexString()}`;
		ctx.strokeStyle = colour;
		ctx.lineWidth = 2;
		ctx.lineCap = 'round';
		ctx.beginPath();
		for ( const [ x0, y0, x1, y1 ] of segments ) {
			ctx.moveTo( x0, y0 );
			ctx.lineTo( x1, y1 );
		}
		ctx.stroke();
		return { part: part.name, colour, segments };
	}

	// Two lines through the point across the picture, open about it (the point shows).
	drawCrosshair( ctx, [ x, y ] ) {
		const r = this.rect;
		const gap = 6;
		ctx.strokeStyle = CROSSHAIR;
		ctx.lineWidth = 1;
		ctx.beginPath();
		for ( const [ a, b ] of [ [ r.x, x - gap ], [ x + gap, r.x + r.w ] ] ) if ( b > a ) ctx.moveTo( a, y ), ctx.lineTo( b, y );
		for ( const [ a, b ] of [ [ r.y, y - gap ], [ y + gap, r.y + r.h ] ] ) if ( b > a ) ctx.moveTo( x, a ), ctx.lineTo( x, b );
		ctx.stroke();
	}
}

export class LinkedSlices {
	// volumePanel: the page's VolumePanel, whose voxels and window the slices share.
	constructor( viewer, volumePanel ) {
		this.viewer = viewer;
		this.volumePanel = volumePanel;
		this.button = $( 'slices-toggle' );
		this.root = $( 'slices' );
		if ( ! this.button || ! this.root || ! volumePanel?.button ) return; // no scan offered
		this.button.hidden = false;
		this.views = NAMES.map( ( name ) => new SliceView( this, name ) );
		this.root.replaceChildren( ...this.views.map( ( v ) => v.root ) );
		this.cache = new WeakMap(); // a part's mesh -> its vertices in voxel coordinates
		this.point = null;
		this.wanted = null; // a point asked for (a room's) before the voxels came
		this.pending = false;
		this.onChange = null; // a person moved the crosshair or turned the slices on or off
		this.button.addEventListener( 'click', () => this.show( ! this.isOn() ) );
		this.bindPage();
		status.slices = { on: false };
	}

	isOn() {
		return this.button?.getAttribute( 'aria-pressed' ) === 'true';
	}

	// Whatever changes what a slice shows draws them again: the window, the parts shown
	// and their colours (the structures list), a new model, the views' size.
	bindPage() {
		const redraw = () => this.redraw();
		$( 'volume-preset' )?.addEventListener( 'change', redraw );
		for ( const id of [ 'volume-level', 'volume-window' ] ) $( id )?.addEventListener( 'input', redraw );
		const structures = $( 'structures-section' );
		for ( const type of [ 'input', 'change', 'click' ] ) structures?.addEventListener( type, redraw );
		if ( $( 'structure-list' ) ) new MutationObserver( redraw ).observe( $( 'structure-list' ), { childList: true } );
		const resized = new ResizeObserver( redraw );
		for ( const view of this.views ) resized.observe( view.canvas );
		// A click (not a drag) on a surface in 3-D: the crosshair goes there.
		onClick( this.viewer.renderer.domElement, ( e ) => {
			if ( ! this.isOn() || ! this.volume || this.viewer.annotating ) return;
			const hit = this.viewer.pick( e.clientX, e.clientY );
			if ( hit ) this.setPoint( hit.lps );
		} );
	}

	// What a room shares of the slices: whether they show and the crosshair (LPS mm).
	state() {
		if ( ! this.button ) return null;
		const point = this.point || this.wanted;
		return { on: this.isOn(), point: point ? [ ...point ] : null };
	}

	// A room's slices: shown or hidden, the crosshair where the presenter put it.
	async apply( state ) {
		if ( ! this.button || ! state ) return;
		if ( state.point ) {
			if ( this.volume ) this.setPoint( state.point, false );
			else this.wanted = [ ...state.point ];
		}
		if ( state.on !== this.isOn() ) await this.show( state.on, false );
	}

	// notify: a person did it (the room hears of it), not a room's message.
	async show( on, notify = true ) {
		if ( ! this.button ) return;
		this.button.setAttribute( 'aria-pressed', String( on ) );
		this.root.hidden = ! on;
		this.root.closest( '.viewer-page' )?.classList.toggle( 'with-slices', on );
		setAddressView( 'slices', on );
		if ( this.marker ) this.marker.visible = on;
		this.viewer.requestRender();
		if ( notify ) this.onChange?.();
		if ( ! on ) {
			setAddressParam( 'at', null );
			status.slices = { on: false };
			return;
		}
		try {
			await this.load();
		} catch ( err ) {
			$( 'volume-note' ).textContent = err.message || String( err );
			status.slices = { on: false, error: String( err.message || err ) };
			return;
		}
		this.placeMarker();
		await this.drawNow();
	}

	async load() {
		if ( this.volume ) return;
		const [ module, body ] = await this.volumePanel.prefetch();
		const { header, data } = module.decode( body );
		this.volume = { header, data, presets: module.presetsFor( header ) };
		this.frame = frameOf( header.affine );
		this.voxelMatrix = new THREE.Matrix4().set( ...header.affine.flat() ).invert();
		for ( const view of this.views ) view.setLayout( layoutOf( this.frame, header.dims, view.name ) );
		const middle = toLps( this.frame, header.dims.map( ( n ) => ( n - 1 ) / 2 ) );
		this.point = this.wanted || addressNumbers( 'at', 3 ) || middle; // a room's, a deep link's, the scan's middle
		this.wanted = null;
		this.followPoint();
		status.lpsToScreen = ( lps ) => {
			const p = this.viewer.toWorld( lps ).project( this.viewer.camera );
			const rect = this.viewer.renderer.domElement.getBoundingClientRect();
			return [ rect.left + ( p.x + 1 ) / 2 * rect.width, rect.top + ( 1 - p.y ) / 2 * rect.height ];
		};
	}

	// The window the slices are drawn with: the volume panel's, else its first preset's.
	windowNow() {
		const layer = this.volumePanel.layer;
		if ( layer ) return [ layer.level, layer.width ];
		const first = Object.values( this.volume.presets )[ 0 ];
		return [ first.level, first.window ];
	}

	// The crosshair at a patient LPS mm point: each view goes to the slice through it.
	setPoint( lps, notify = true ) {
		if ( ! this.volume ) return;
		this.point = [ ...lps ];
		this.followPoint();
		this.placeMarker();
		this.redraw();
		setAddressParam( 'at', this.point.map( ( x ) => Number( x.toFixed( 1 ) ) ).join( ',' ), 250 );
		if ( notify ) this.onChange?.();
	}

	followPoint() {
		const c = toVoxel( this.frame, this.point );
		for ( const view of this.views ) view.index = Math.min( view.layout.count - 1, Math.max( 0, Math.round( c[ view.layout.s ] ) ) );
	}

	// A view steps `delta` slices: the crosshair moves across to the new slice's plane.
	step( view, delta ) {
		const to = Math.min( view.layout.count - 1, Math.max( 0, view.index + delta ) );
		if ( to === view.index ) return;
		const c = toVoxel( this.frame, this.point );
		c[ view.layout.s ] = to;
		this.setPoint( toLps( this.frame, c ) );
	}

	// A part's vertices in voxel coordinates (once a mesh) and its triangles.
	voxelsOf( part ) {
		let found = this.cache.get( part.mesh );
		if ( ! found ) {
			part.mesh.updateWorldMatrix( true, false );
			const matrix = this.voxelMatrix.clone().multiply( this.viewer.lpsToWorld.clone().invert() ).multiply( part.mesh.matrixWorld );
			const position = part.mesh.geometry.attributes.position;
			const voxels = new Float32Array( position.count * 3 );
			const v = new THREE.Vector3();
			for ( let i = 0; i < position.count; i ++ ) v.fromBufferAttribute( position, i ).applyMatrix4( matrix ).toArray( voxels, 3 * i );
			found = { voxels, index: part.mesh.geometry.index?.array || null };
			this.cache.set( part.mesh, found );
		}
		return found;
	}

	// The 3-D view's clipping plane as a signed distance over voxel coordinates (kept
	// where >= 0), or null while nothing is clipped.
	clipInVoxels() {
		if ( ! this.viewer.clipping ) return null;
		const toWorld = this.viewer.lpsToWorld.clone().multiply( this.voxelMatrix.clone().invert() );
		const plane = this.viewer.clipPlane.clone().applyMatrix4( toWorld.invert() );
		const v = new THREE.Vector3();
		return ( c ) => plane.distanceToPoint( v.set( c[ 0 ], c[ 1 ], c[ 2 ] ) );
	}

	// The crosshair in 3-D: a small sphere drawn over the surfaces.
	placeMarker() {
		if ( ! this.marker ) {
			this.marker = new THREE.Mesh( new THREE.SphereGeometry( 1, 16, 12 ), new THREE.MeshBasicMaterial( { color: 0xffd400, depthTest: false } ) );
			this.marker.name = 'crosshair';
			this.marker.renderOrder = 20;
			this.viewer.scene.add( this.marker );
		}
		const [ at, size ] = [ this.viewer.toWorld( this.point ), this.viewer.radius() * 0.02 ];
		if ( this.marker.visible === this.isOn() && this.marker.position.equals( at ) && this.marker.scale.x === size ) return;
		this.marker.visible = this.isOn();
		this.marker.position.copy( at );
		this.marker.scale.setScalar( size );
		this.viewer.requestRender();
	}

	// Drawn in the next animation frame, once however many changes came before it.
	redraw() {
		if ( this.pending || ! this.isOn() || ! this.volume ) return;
		this.pending = true;
		requestAnimationFrame( () => {
			this.pending = false;
			this.drawNow();
		} );
	}

	drawNow() {
		if ( ! this.isOn() || ! this.volume ) return;
		const window = this.windowNow();
		const parts = this.viewer.parts.filter( ( p ) => p.mesh.visible && p.material.visible !== false && p.material.opacity > 0 );
		this.placeMarker(); // the model may have come since (its size, its frame)
		const views = Object.fromEntries( this.views.map( ( v ) => [ v.name, v.draw( this.point, window, parts ) ] ) );
		status.slices = { on: true, point: [ ...this.point ], window, affine: this.volume.header.affine, views, drawnAt: performance.now() };
	}
}
