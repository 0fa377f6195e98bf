// Volume upload. XMLHttpRequest rather than fetch because only XHR reports
// upload progress (upload.onprogress), and a 500 MB DICOM zip needs a bar.

import { ApiError, csrfToken, detailText, loginUrl } from './api.js';

// Resolves with the new volume's JSON; onProgress(fraction, phase) where
// phase is 'sending' while bytes go out and 'reading' once they are all sent
// and the server parses the series (which can take a while for DICOM).
export function uploadVolume( file, onProgress = () => {} ) {
	return new Promise( ( resolve, reject ) => {
		const xhr = new XMLHttpRequest();
		xhr.open( 'POST', '/api/volumes' );
		xhr.setRequestHeader( 'Accept', 'application/json' );
		xhr.setRequestHeader( 'X-CSRF-Token', csrfToken() );
		xhr.responseType = 'text';
		xhr.upload.onprogress = ( event ) => {
			if ( event.lengthComputable ) onProgress( event.loaded / event.total, 'sending' );
		};
		xhr.upload.onload = () => onProgress( 1, 'reading' );
		xhr.onload = () => {
			let body = null;
			try {
				body = xhr.responseText ? JSON.parse( xhr.responseText ) : null;
			} catch ( err ) {
				body = { detail: xhr.responseText };
			}
			if ( xhr.status === 401 ) location.assign( loginUrl() );
			if ( xhr.status >= 200 && xhr.status < 300 ) resolve( body );
			else reject( new ApiError( xhr.status, detailText( body, xhr.status ) ) );
		};
		xhr.onerror = () => reject( new ApiError( 0, 'the upload was interrupted; check the connection and try again' ) );
		xhr.onabort = () => reject( new ApiError( 0, 'upload cancelled' ) );
		const form = new FormData();
		form.append( 'file', file, file.name );
		xhr.send( form );
	} );
}

// The server decides what it can read; this only catches the obvious mistake
// (a PDF, a folder) before sending bytes.
export const ACCEPT = [ '.zip', '.nii', '.nii.gz', '.nrrd', '.mha' ];

export function looksLikeVolume( name ) {
	const lower = name.toLowerCase();
	return ACCEPT.some( ( ext ) => lower.endsWith( ext ) );
}
