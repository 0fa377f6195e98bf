// Small helpers shared by the pages: DOM building and number formatting.

// el('a#id.button.small', {href}, 'text', child) — enough of a hyperscript to keep
// page code declarative without a framework.
// The attributes object may be left out: el('div.facts', 'text').
export function el( spec, attrs = {}, ...children ) {
	if ( attrs === null || typeof attrs !== 'object' || attrs instanceof Node || Array.isArray( attrs ) ) {
		children.unshift( attrs );
		attrs = {};
	}
	const [ head, ...classes ] = spec.split( '.' );
	const [ tag, id ] = head.split( '#' );
	const node = document.createElement( tag || 'div' );
	if ( id ) node.id = id;
	if ( classes.length ) node.className = classes.join( ' ' );
	for ( const [ key, value ] of Object.entries( attrs ) ) {
		if ( value == null || value === false ) continue;
		if ( key.startsWith( 'on' ) ) node.addEventListener( key.slice( 2 ), value );
		else if ( key === 'dataset' ) Object.assign( node.dataset, value );
		// Through the CSSOM: a style attribute would need 'unsafe-inline' in the CSP.
		else if ( key === 'style' ) node.style.cssText = String( value );
		else node.setAttribute( key, value === true ? '' : String( value ) );
	}
	for ( const child of children.flat() ) {
		if ( child == null || child === false ) continue;
		node.append( child instanceof Node ? child : document.createTextNode( String( child ) ) );
	}
	return node;
}

// node.replaceChildren, skipping null/false children (optional rows) instead of
// writing them as text.
export function fill( node, ...children ) {
	node.replaceChildren( ...children.flat().filter( ( c ) => c != null && c !== false ) );
	return node;
}

export function formatBytes( n ) {
	if ( n == null || ! Number.isFinite( n ) ) return '–';
	if ( n < 1024 ) return `${n} B`;
	const units = [ 'KB', 'MB', 'GB' ];
	let v = n / 1024;
	let i = 0;
	while ( v >= 1024 && i < units.length - 1 ) {
		v /= 1024;
		i ++;
	}
	return `${v < 10 ? v.toFixed( 1 ) : Math.round( v )} ${units[ i ]}`;
}

export function formatSeconds( s ) {
	if ( s == null || ! Number.isFinite( s ) ) return '–';
	return s < 10 ? `${s.toFixed( 2 )} s` : `${s.toFixed( 1 )} s`;
}

export function formatCount( n ) {
	return n == null ? '–' : Number( n ).toLocaleString( 'en-US' );
}

export function formatMm( v, digits = 3 ) {
	return v == null || ! Number.isFinite( v ) ? '–' : `${v.toFixed( digits )} mm`;
}

// What kind of scan, as a person names it: the modality its header gives (CT, MR ...),
// else its file format (NIfTI, NRRD and MetaImage carry no modality).
const FORMAT_NAMES = { dicom: 'DICOM', nifti: 'NIfTI', nrrd: 'NRRD', metaimage: 'MetaImage' };
export function modalityLabel( v ) {
	return v.modality || FORMAT_NAMES[ v.source_format ] || 'Scan';
}

export function describeVolume( v ) {
	const dims = ( v.dims || [] ).join( ' × ' );
	return `${modalityLabel( v )} · ${dims} voxels · ${spacingMm( v ).join( ' × ' )} mm`;
}

// mm between voxels as MISS used them (x, y, z), rounded to µm: z is the distance between
// slice planes along their normal, less than the stored z step when a gantry tilt shears them.
function spacingMm( v ) {
	const [ sx, sy, sz ] = ( v.spacing || [] ).map( ( s ) => +Number( s ).toFixed( 3 ) );
	const gap = v.slice_gap != null ? +Number( v.slice_gap ).toFixed( 3 ) : sz;
	return [ sx, sy, gap ];
}

// The spacing MISS used, in words, with the step along a tilted stack when it differs.
export function spacingAsUsed( v ) {
	const [ sx, sy, gap ] = spacingMm( v );
	const sz = +Number( ( v.spacing || [] )[ 2 ] ).toFixed( 3 );
	const along = gap !== sz ? `; ${sz} mm along the tilted stack` : '';
	return `${sx} × ${sy} × ${gap} mm (across × down × between slices${along})`;
}

// What MISS changed in reading the scan (a gantry tilt, uneven gaps resampled, ...): its
// notes said plainly and the spacing as used, into `root` (a <details>, open: issue 42 was
// that nobody saw them); hidden when nothing changed.
export function showNotes( root, v ) {
	const notes = v.notes_plain || v.notes || [];
	root.hidden = notes.length === 0;
	root.open = true;
	root.replaceChildren(
		el( 'summary', {}, `What MISS changed in reading the scan (${notes.length})` ),
		el( 'ul', {}, ...notes.map( ( n ) => el( 'li', {}, n.replace( /\.?$/, '.' ) ) ) ),
		el( 'p.spacing', {}, `Spacing as used: ${spacingAsUsed( v )}.` ),
	);
}

const CLICK_SLOP = 5; // pixels a press may move and still count as a click, not a turn

// Calls handler(event) for a press released where it started: a click, not an orbit drag.
export function onClick( target, handler ) {
	let down = null;
	target.addEventListener( 'pointerdown', ( e ) => {
		down = { x: e.clientX, y: e.clientY };
	} );
	target.addEventListener( 'pointerup', ( e ) => {
		const click = down && Math.hypot( e.clientX - down.x, e.clientY - down.y ) < CLICK_SLOP;
		down = null;
		if ( click ) handler( e );
	} );
}
