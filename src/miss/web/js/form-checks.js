// The job form's values checked where they are typed, with the volume's own limits and
// in the form's numbering (slices 1..N): the same refusals the server makes (miss.spec),
// said at the field at once rather than after Generate. Each check returns '' when the
// value is fine, else the sentence to show.

// A level the volume's values surround: lo < level < hi (a level at or beyond an end
// has no surface).
export function checkLevel( text, [ lo, hi ], units = '', what = 'Threshold' ) {
	const unit = units ? ` ${units}` : '';
	if ( text.trim() === '' ) return `${what}: give a level between ${lo} and ${hi}${unit}.`;
	const v = Number( text );
	if ( ! Number.isFinite( v ) ) return `${what} “${text}” is not a number; give a level between ${lo} and ${hi}${unit}.`;
	if ( v <= lo || v >= hi ) return `${what} ${v} is outside this volume's values ${lo}..${hi}${unit}; pick a level between them (the presets are).`;
	return '';
}

// Every n-th voxel: one whole number >= 1, or three of them as x,y,z.
export function parseSampleRate( text ) {
	const parts = text.split( ',' ).map( ( s ) => s.trim() );
	if ( ( parts.length !== 1 && parts.length !== 3 ) || ! parts.every( ( p ) => /^[1-9]\d*$/.test( p ) ) ) return null;
	return parts.map( Number );
}

export function checkSampleRate( text ) {
	return parseSampleRate( text ) ? '' : `Sample rate “${text.trim()}” is not one whole number ≥ 1 or three as x,y,z; type e.g. 2 or 1,1,2.`;
}

// Start and end slice, 1-based and inclusive, of a stack of n; at sample rate `step` along
// the slices a surface needs at least 2 of them.
export function checkSlices( startText, endText, n, step = 1 ) {
	const whole = ( t ) => /^\s*\d+\s*$/.test( t ) ? Number( t ) : null;
	const start = whole( startText );
	const end = whole( endText );
	if ( start === null || start < 1 || start > n ) return { field: 'start', message: `Start slice must be a whole number from 1 to ${n}.` };
	if ( end === null || end < 1 || end > n ) return { field: 'end', message: `End slice must be a whole number from 1 to ${n}.` };
	if ( start > end ) return { field: 'start', message: `Start slice ${start} is after end slice ${end}; choose a start before the end (1..${n}).` };
	if ( Math.floor( ( end - start ) / step ) < 1 ) {
		const held = start === end ? `slice ${start} alone` : `slices ${start}..${end} at sample rate ${step}`;
		return { field: 'end', message: `A surface needs at least 2 slices; ${held} give${start === end ? 's' : ''} one: choose an end slice from ${start + step} or a lower sample rate.` };
	}
	return null;
}

// Marks `input` invalid with `message` ('' clears it), shown at the field: the browser's
// bubble on Generate says the same sentence.
export function showCheck( input, message ) {
	input.setCustomValidity( message );
	input.setAttribute( 'aria-invalid', String( Boolean( message ) ) );
	let note = input.parentElement.querySelector( ':scope > .field-error' );
	if ( ! note && message ) {
		note = document.createElement( 'span' );
		note.className = 'field-error';
		note.id = `${input.id || 'field'}-error`;
		note.setAttribute( 'role', 'alert' );
		input.after( note );
		input.setAttribute( 'aria-describedby', note.id );
	}
	if ( note ) {
		note.textContent = message;
		note.hidden = ! message;
	}
}
