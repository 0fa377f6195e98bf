// Names and colours the user gives structures on the volume page. The server
// names a level's part itself ("bone (300 HU)", "level 300", "… 2" when split),
// so these are kept in the browser per model and applied by level in the viewer.

const KEY = ( modelId ) => `miss.structures.${modelId}`;

// styles: [{level, name, color}] in the order of the request's levels.
export function saveStyles( modelId, styles ) {
	try {
		localStorage.setItem( KEY( modelId ), JSON.stringify( styles ) );
	} catch {
		// private mode or full storage: the server's names stay
	}
}

export function loadStyles( modelId ) {
	try {
		return JSON.parse( localStorage.getItem( KEY( modelId ) ) || '[]' );
	} catch {
		return [];
	}
}

// Python's `{:g}` for the numbers a form sends (integers and short decimals).
function g( value ) {
	return String( Number( value ) );
}

// The style whose level the server's part name carries, and the piece suffix (" 2").
export function styleFor( partName, styles ) {
	for ( const s of styles ) {
		const L = g( s.level );
		const m = partName.match( new RegExp( `^(?:level ${L.replace( '.', '\\.' )}|[a-z ]+ \\(${L.replace( '.', '\\.' )} [^)]*\\))( \\d+)?$` ) );
		if ( m ) return { style: s, suffix: m[ 1 ] || '' };
	}
	return null;
}
