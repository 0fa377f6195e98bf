// The camera in the address: ?cam=px,py,pz,tx,ty,tz,ux,uy,uz (where the eye is, what it
// looks at, which way is up; patient LPS mm), so that a physician who copies the address
// (or a share link with it) sends exactly the view they see. Kept in step as the view
// turns, without adding history entries.

const DIGITS = 2;

export function cameraFromUrl( search = location.search ) {
	const v = addressNumbers( 'cam', 9, search );
	if ( ! v ) return null; // none, or a mangled link: the default view
	const up = v.slice( 6 );
	if ( Math.hypot( ...up ) < 1e-6 || Math.hypot( v[ 0 ] - v[ 3 ], v[ 1 ] - v[ 4 ], v[ 2 ] - v[ 5 ] ) < 1e-6 ) return null;
	return { position: v.slice( 0, 3 ), target: v.slice( 3, 6 ), up };
}

function encode( pose ) {
	return [ ...pose.position, ...pose.target, ...pose.up ].map( ( x ) => Number( x.toFixed( DIGITS ) ) ).join( ',' );
}

// After the model is drawn: take the view from the address (if any), then keep the
// address following the view.
export function linkCamera( viewer ) {
	const pose = cameraFromUrl();
	if ( pose ) viewer.setWorldPose( viewer.toWorld( pose.position ), viewer.toWorld( pose.target ),
		viewer.lpsDirectionToWorld( pose.up ) );
	let timer = 0;
	viewer.onCameraChange( () => {
		clearTimeout( timer );
		timer = setTimeout( () => {
			const url = new URL( location.href );
			url.searchParams.set( 'cam', encode( viewer.pose() ) );
			history.replaceState( history.state, '', url );
		}, 250 );
	} );
}

// The views an address asks for besides the surfaces: ?view=volume, ?view=slices or both
// (?view=volume,slices); each panel keeps its own name in the address in step.
export function addressViews( search = location.search ) {
	return new Set( ( new URLSearchParams( search ).get( 'view' ) || '' ).split( ',' ).filter( Boolean ) );
}

export function setAddressView( name, on ) {
	const views = addressViews();
	if ( on ) views.add( name );
	else views.delete( name );
	const url = new URL( location.href );
	if ( views.size ) url.searchParams.set( 'view', [ ...views ].join( ',' ) );
	else url.searchParams.delete( 'view' );
	history.replaceState( history.state, '', url );
}

// One more part of the view in the address (the scan's preset and window, the slices'
// crosshair), null to leave it out; written after `delay` ms of quiet (a drag writes once).
const pending = new Map();
export function setAddressParam( name, value, delay = 0 ) {
	clearTimeout( pending.get( name ) );
	pending.set( name, setTimeout( () => {
		const url = new URL( location.href );
		if ( value == null ) url.searchParams.delete( name );
		else url.searchParams.set( name, value );
		history.replaceState( history.state, '', url );
	}, delay ) );
}

// `count` finite numbers from ?name=a,b,...; null when absent or mangled.
export function addressNumbers( name, count, search = location.search ) {
	const raw = new URLSearchParams( search ).get( name );
	if ( ! raw ) return null;
	const v = raw.split( ',' ).map( Number );
	return v.length === count && v.every( Number.isFinite ) ? v : null;
}

export function addressParam( name, search = location.search ) {
	return new URLSearchParams( search ).get( name );
}

// The view in this page's address that a share link may carry: the camera, and with the
// scan (a link that offers it) the volume and slices, preset, window and crosshair.
export function viewParams( withScan, search = location.search ) {
	const names = withScan ? [ 'cam', 'view', 'preset', 'wl', 'at' ] : [ 'cam' ];
	const params = new URLSearchParams( search );
	return names.filter( ( n ) => params.has( n ) ).map( ( n ) => [ n, params.get( n ) ] );
}
