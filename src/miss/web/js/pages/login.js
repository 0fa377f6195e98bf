// Login page: name and password to POST /api/auth/login; the server sets the
// session cookie, and the browser goes back where it came from.

import { api } from '../api.js';

const $ = ( id ) => document.getElementById( id );

// Only a path on this server: an open redirect would let a phishing link bounce
// through MISS's own login page. Browsers read "/\\host", "/\thost" and "//host" as
// another host, so the path must start with one "/" followed by neither "/" nor "\\",
// hold no control characters or spaces, and resolve to this origin.
export function safeNext( next ) {
	if ( typeof next !== 'string' || ! /^\/(?![\/\\])/.test( next ) ) return '/';
	if ( /[\u0000-\u0020\u007f-\u00a0\\]/.test( next ) ) return '/';
	try {
		const url = new URL( next, location.origin );
		return url.origin === location.origin ? url.pathname + url.search + url.hash : '/';
	} catch {
		return '/';
	}
}

function nextPath() {
	return safeNext( new URLSearchParams( location.search ).get( 'next' ) || '/' );
}

$( 'login' ).addEventListener( 'submit', async ( event ) => {
	event.preventDefault();
	$( 'submit' ).disabled = true;
	$( 'login-error' ).hidden = true;
	try {
		await api.login( $( 'username' ).value.trim(), $( 'password' ).value );
		location.assign( nextPath() );
	} catch ( err ) {
		$( 'login-error' ).textContent = err.message || String( err );
		$( 'login-error' ).hidden = false;
		$( 'password' ).select();
	} finally {
		$( 'submit' ).disabled = false;
	}
} );

document.body.dataset.ready = '1';
