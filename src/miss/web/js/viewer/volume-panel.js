// The "Volume" section of the model page: a toggle that shows the scan itself in the 3-D
// view (volume.js, loaded the first time it is asked for), its presets and its window.
// ?view=volume in the address turns it on as the page opens (a deep link), ?preset= and
// ?wl=level,window pick its look; the panel keeps the address in step.

import { status } from '../test-hooks.js';
import { CUSTOM, pointsAt, TransferEditor } from './tf-editor.js';
import { addressNumbers, addressParam, setAddressParam, setAddressView } from './deep-link.js';

const $ = ( id ) => document.getElementById( id );

export class VolumePanel {
	// `voxelsUrl`: where the voxels come from (the owner's API, or a share link's
	// /s/{token}/voxels when its owner offered the scan).
	constructor( viewer, voxelsUrl ) {
		this.viewer = viewer;
		this.voxelsUrl = voxelsUrl;
		this.layer = null;
		this.loading = null;
		this.onChange = null; // a person changed the view (a room passes it on), not apply()
		this.button = $( 'volume-toggle' );
		if ( ! this.button ) return; // a page without the section
		$( 'volume-section' ).hidden = false;
		this.button.hidden = false;
		// Said at once, and again once done (a first showing loads the preset and window).
		const changed = ( done ) => {
			this.onChange?.();
			Promise.resolve( done ).then( () => this.onChange?.() );
		};
		this.button.addEventListener( 'click', () => changed( this.show( ! this.isOn() ) ) );
		$( 'volume-preset' ).addEventListener( 'change', ( e ) => changed( this.setPreset( e.target.value ) ) );
		for ( const id of [ 'volume-level', 'volume-window' ] ) $( id ).addEventListener( 'input', () => changed( this.setWindow() ) );
		$( 'volume-full' ).addEventListener( 'click', () => this.full() );
	}

	isOn() {
		return this.button?.getAttribute( 'aria-pressed' ) === 'true';
	}

	// What a room shares of the scan's view: shown or not, its preset and window (and an
	// edited transfer function's points, in the volume's units at that window).
	state() {
		const l = this.layer;
		if ( ! l ) return { on: this.isOn(), preset: null, level: null, window: null, points: null };
		const points = l.preset === CUSTOM ? pointsAt( l.presets[ CUSTOM ], l.level, l.width ) : null;
		return { on: this.isOn(), preset: l.preset, level: l.level, window: l.width, points };
	}

	// Shows what a room says (the presenter's or the owner's view), without passing it on.
	// A page without the scan (a link that does not offer it) shows the surfaces alone.
	async apply( view ) {
		if ( ! view || ! this.button ) return;
		if ( view.on !== this.isOn() ) await this.show( view.on );
		if ( ! view.on || ! this.layer ) return;
		if ( view.preset === CUSTOM && view.points ) {
			this.layer.presets[ CUSTOM ] = { level: view.level, window: view.window, points: view.points };
			const select = $( 'volume-preset' );
			if ( ! [ ...select.options ].some( ( o ) => o.value === CUSTOM ) ) select.add( new Option( CUSTOM, CUSTOM ) );
			this.layer.preset = null; // set again below, with the new points
		}
		if ( view.preset && view.preset in this.layer.presets && view.preset !== this.layer.preset ) {
			this.layer.setPreset( view.preset );
			$( 'volume-preset' ).value = view.preset;
		}
		if ( view.level != null && view.window > 0 ) this.layer.setWindow( view.level, view.window );
		this.fillWindow();
		this.editor?.draw();
		await this.drawn();
	}

	// The voxels and the renderer's module, fetched once (a deep link asks before the
	// model is drawn, so both arrive while it loads).
	prefetch() {
		if ( ! this.loading ) {
			const body = fetch( `${this.voxelsUrl}?level=0`, { credentials: 'same-origin' } ).then( ( r ) => {
				if ( ! r.ok ) throw new Error( `the scan's voxels could not be fetched (${r.status})` );
				return r.arrayBuffer();
			} ).then( ( b ) => ( performance.mark( 'volume:voxels' ), b ) ); // the benchmark's split
			this.loading = Promise.all( [ import( './volume.js' ), body ] );
			this.loading.catch( () => {} );
		}
		return this.loading;
	}

	// on: shown or not. staged: a promise of the model on the stage (a deep link shows the
	// volume while the model loads, so that the model's first frame has it; its picture
	// counts from then).
	async show( on, staged = null ) {
		if ( ! this.button ) return;
		this.button.setAttribute( 'aria-pressed', String( on ) );
		$( 'volume-controls' ).hidden = ! on;
		setAddressView( 'volume', on );
		if ( ! on ) {
			setAddressParam( 'preset', null );
			setAddressParam( 'wl', null );
			if ( this.layer ) this.layer.mesh.visible = false;
			if ( status.softwareWebGL ) this.viewer.setCoarse( false );
			status.volume = { ...status.volume, on: false };
			return this.viewer.requestRender();
		}
		try {
			await this.load();
		} catch ( err ) {
			$( 'volume-note' ).textContent = err.message || String( err );
			status.volume = { on: false, error: String( err.message || err ) };
			return;
		}
		const frames = status.volumeFrames || 0;
		this.layer.mesh.visible = true;
		// Software WebGL pays for every ray: half the pixels a side while the volume shows.
		if ( status.softwareWebGL ) this.viewer.setCoarse( true );
		await staged;
		await this.drawn( ( status.volumeFrames || 0 ) > frames );
	}

	async load() {
		if ( this.layer ) return;
		$( 'volume-note' ).textContent = 'Loading the scan…';
		const [ module, body ] = await this.prefetch();
		const { header, data } = module.decode( body );
		this.layer = new module.VolumeLayer( header, data, this.viewer.lpsToWorld );
		this.viewer.setVolume( this.layer );
		performance.mark( 'volume:layer' );
		// A deep link's look: its preset, then its window (a Custom curve is not in addresses).
		const preset = addressParam( 'preset' );
		if ( preset && preset !== CUSTOM && preset in this.layer.presets ) this.layer.setPreset( preset );
		const wl = addressNumbers( 'wl', 2 );
		if ( wl && wl[ 1 ] > 0 ) this.layer.setWindow( wl[ 0 ], wl[ 1 ] );
		this.addHooks();
		const select = $( 'volume-preset' );
		select.replaceChildren( ...Object.keys( this.layer.presets ).map( ( name ) => new Option( name, name ) ) );
		select.value = this.layer.preset;
		this.fillWindow();
		this.editor = new TransferEditor( this, { canvas: $( 'tf-canvas' ), colour: $( 'tf-colour' ), note: $( 'tf-note' ) } );
		this.describe();
	}

	describe() {
		const { dims: [ nx, ny, nz ], factors } = this.layer.header;
		const coarse = factors.some( ( f ) => f > 1 );
		$( 'volume-note' ).textContent = `${nx} × ${ny} × ${nz} voxels${coarse ? ' (a coarse level)' : ''}`;
		$( 'volume-full' ).hidden = ! coarse || this.layer.header.level === 1;
	}

	// Level 1, the scan at full resolution within the server's budget, in place of the
	// first picture's level: asked for with a click (megabytes, and slower turning), the
	// preset, window and edited transfer function kept.
	async full() {
		const button = $( 'volume-full' );
		button.disabled = true;
		$( 'volume-note' ).textContent = 'Loading the full resolution…';
		try {
			const r = await fetch( `${this.voxelsUrl}?level=1`, { credentials: 'same-origin' } );
			if ( ! r.ok ) throw new Error( `the full resolution could not be fetched (${r.status})` );
			const [ module, body ] = await Promise.all( [ import( './volume.js' ), r.arrayBuffer() ] );
			const { header, data } = module.decode( body );
			const old = this.layer;
			const layer = new module.VolumeLayer( header, data, this.viewer.lpsToWorld );
			if ( old.presets[ CUSTOM ] ) layer.presets[ CUSTOM ] = old.presets[ CUSTOM ];
			layer.setPreset( old.preset );
			layer.setWindow( old.level, old.width );
			layer.mesh.visible = old.mesh.visible;
			this.layer = layer;
			this.viewer.setVolume( layer );
			this.editor?.useVoxels( data );
			this.describe();
		} catch ( err ) {
			$( 'volume-note' ).textContent = err.message || String( err );
		} finally {
			button.disabled = false;
		}
		if ( this.isOn() ) await this.drawn();
	}

	// What the benchmark and the tests ask the page (window.__miss).
	addHooks() {
		// For the benchmark: frames while turning, one after another as a drag asks for them
		// (each turned about the target, then drawn to finished), ms each.
		status.timeVolumeFrames = async ( n = 5, turn = 0.05 ) => {
			const times = [];
			for ( let i = 0; i < n; i ++ ) {
				const t = performance.now();
				this.turn( turn );
				await this.viewer.whenDrawn();
				times.push( performance.now() - t );
			}
			return times;
		};
		// ... and the full frame once the turning stops: from asked for to finished, ms.
		status.timeSettledFrame = async ( turn = 0.05 ) => {
			this.turn( turn );
			await this.viewer.whenSettled();
			return performance.now() - this.viewer.volumePass.fullStartedAt;
		};
		// For the tests: the next frame as a PNG data URL (read in the task that drew it) and
		// its quality ('fast' or 'full'), after turning the camera by an angle (radians).
		status.grabVolumeFrame = ( turn = 0 ) => new Promise( ( resolve ) => {
			if ( turn ) this.turn( turn );
			this.viewer.afterRender.push( () => resolve( {
				quality: this.viewer.volumePass.quality, png: this.viewer.renderer.domElement.toDataURL(),
			} ) );
			this.viewer.requestRender();
		} );
		// For the tests: where a voxel of the sent grid lands on the canvas (CSS pixels).
		status.voxelToScreen = ( ijk ) => {
			const p = new this.viewer.camera.position.constructor( ...ijk ).applyMatrix4( this.layer.mesh.matrixWorld ).project( this.viewer.camera );
			const rect = this.viewer.renderer.domElement.getBoundingClientRect();
			return [ ( p.x + 1 ) / 2 * rect.width, ( 1 - p.y ) / 2 * rect.height ];
		};
	}

	// status.volume once the change is drawn in full (firstAt: its first, fast picture;
	// asked for already, or not yet).
	async drawn( asked = false ) {
		await ( asked ? new Promise( ( resolve ) => this.viewer.fence( resolve ) ) : this.viewer.whenDrawn() );
		const firstAt = performance.now();
		await this.viewer.whenSettled();
		status.volume = {
			on: true, preset: this.layer.preset, level: this.layer.level, window: this.layer.width,
			dims: this.layer.header.dims, frames: status.volumeFrames, firstAt, drawnAt: performance.now(),
		};
		if ( this.isOn() ) {
			setAddressParam( 'preset', this.layer.preset === CUSTOM ? null : this.layer.preset );
			setAddressParam( 'wl', `${Math.round( this.layer.level )},${Math.round( this.layer.width )}`, 250 );
		}
	}

	// The camera turned about its target by an angle (radians), as a drag does.
	turn( angle ) {
		const { camera, controls } = this.viewer;
		camera.position.sub( controls.target ).applyAxisAngle( camera.up, angle ).add( controls.target );
		camera.lookAt( controls.target );
	}

	fillWindow() {
		$( 'volume-level' ).value = String( Math.round( this.layer.level ) );
		$( 'volume-window' ).value = String( Math.round( this.layer.width ) );
	}

	setPreset( name ) {
		if ( ! this.layer ) return;
		this.layer.setPreset( name );
		this.fillWindow();
		this.editor?.draw();
		return this.drawn();
	}

	// The transfer function's editor made the Custom preset: show it and say so.
	useCustom() {
		const select = $( 'volume-preset' );
		if ( ! [ ...select.options ].some( ( o ) => o.value === CUSTOM ) ) select.add( new Option( CUSTOM, CUSTOM ) );
		select.value = CUSTOM;
		this.layer.setPreset( CUSTOM );
		this.fillWindow();
		this.drawn();
		this.onChange?.();
	}

	setWindow() {
		const level = Number( $( 'volume-level' ).value );
		const width = Number( $( 'volume-window' ).value );
		if ( ! this.layer || ! Number.isFinite( level ) || ! ( width > 0 ) ) return;
		this.layer.setWindow( level, width );
		this.editor?.draw();
		return this.drawn();
	}
}
